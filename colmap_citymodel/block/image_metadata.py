"""What a photograph's metadata says of where and how it was taken: the EXIF GPS tags, a drone's
XMP (DJI's `drone-dji` namespace; the Pix4D `Camera` namespace that other survey cameras write)
and the camera that took it (EXIF make, model, serial number, focal length, image size).

Position: latitude and longitude from the XMP when it has them (DJI `GpsLatitude`,
`GpsLongitude`, also spelt `GpsLongtitude` by older firmware), else from EXIF GPS; the height
from DJI's `AbsoluteAltitude`, else EXIF `GPSAltitude`. Both are heights above sea level by
definition; DJI's RTK drones may write ellipsoidal heights there (`AltitudeType`, kept in the
record): refine's `--gnss_height_offset auto` estimates such an offset from the model.

Accuracy (`ImageMetadata.sigma`), the first of:
1. an RTK solution (DJI `RtkFlag` > 0 with `RtkStdLon`, `RtkStdLat`, `RtkStdHgt` in metres):
   those standard deviations as the east, north and height sigmas, none below `MIN_RTK_SIGMA`;
2. EXIF `GPSHPositioningError` (metres): sigma_h, and sigma_z = sigma_h * 5/3;
3. the Pix4D camera tags `GPSXYAccuracy`, `GPSZAccuracy` (metres);
4. EXIF `GPSDOP` times `dop_scale` (metres; phones and mapping apps store their accuracy
   estimate in metres there): sigma_h, sigma_z = sigma_h * 5/3;
5. none (the caller's default).

Attitude: DJI's gimbal and aircraft yaw, pitch and roll (degrees, NED, rotation order ZYX: yaw
clockwise from north, pitch -90 looking straight down). They are read and reported (refine has
no orientation prior); `attitude_view` turns the gimbal angles into the viewing direction.

Only the file's header is read, never the pixels; a damaged or missing tag leaves its field
empty (NaN or None) with a warning in `ImageMetadata.warnings`.
"""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

NAN = float("nan")
#: The image files COLMAP's image reader takes (FreeImage) that cameras write.
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".tif", ".tiff", ".png", ".webp")
#: Folders with more images than this show a progress bar while their headers are read.
PROGRESS_MIN_IMAGES = 200
#: XMP namespace of DJI's drone tags.
DJI_NAMESPACE = "http://www.dji.com/drone-dji/1.0/"
#: XMP namespace of Pix4D's camera tags (Sentera, Parrot, MicaSense and others write it).
CAMERA_NAMESPACE = "http://pix4d.com/camera/1.0/"
RDF_NAMESPACE = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"
#: Smallest RTK sigma, metres (east, north, height): DJI's stated RTK positioning accuracy
#: (1 cm + 1 ppm horizontally, 1.5 cm + 1 ppm vertically); the standard deviations a receiver
#: reports for a fixed solution are often smaller than what the image positions reach.
MIN_RTK_SIGMA = (0.01, 0.01, 0.015)
#: sigma_z / sigma_h when a source states one horizontal accuracy (the ratio of the default
#: GNSS sigmas, 5 m / 3 m: satellite geometry makes heights worse than positions).
HEIGHT_TO_HORIZONTAL = 5.0 / 3.0
#: DJI RtkFlag values: 0 no position, 16 single point, 32-49 float, 50 fixed.
RTK_FIXED, RTK_FLOAT_MIN, RTK_SINGLE = 50, 32, 16


@dataclass
class ImageMetadata:
    """One image's position, accuracy, attitude and camera as its EXIF and XMP give them."""

    name: str
    width: int | None = None
    height: int | None = None
    make: str = ""
    model: str = ""
    serial: str = ""
    focal_length_mm: float = NAN
    latitude: float = NAN  # degrees
    longitude: float = NAN
    altitude: float = NAN  # metres, as written (see the module docstring)
    position_source: str | None = None  # "xmp" or "exif"
    altitude_source: str | None = None  # "xmp" or "exif"
    altitude_type: str | None = None  # DJI AltitudeType, e.g. "RtkAlt"
    relative_altitude: float = NAN  # DJI: metres above the take-off point
    gps_dop: float = NAN
    gps_error: float = NAN  # EXIF GPSHPositioningError, metres
    xmp_accuracy: tuple[float, float] | None = None  # Pix4D GPSXYAccuracy, GPSZAccuracy
    rtk_flag: int | None = None
    rtk_std: tuple[float, float, float] | None = None  # east (lon), north (lat), height; m
    gimbal: tuple[float, float, float] | None = None  # yaw, pitch, roll; degrees
    flight: tuple[float, float, float] | None = None  # aircraft yaw, pitch, roll; degrees
    warnings: list[str] = field(default_factory=list)

    @property
    def has_position(self) -> bool:
        return (math.isfinite(self.latitude) and math.isfinite(self.longitude)
                and math.isfinite(self.altitude))

    @property
    def rtk_status(self) -> str | None:
        """"fixed", "float", "single", "none" (RtkFlag 0) or None (no RTK tag)."""
        if self.rtk_flag is None:
            return None
        if self.rtk_flag >= RTK_FIXED:
            return "fixed"
        if self.rtk_flag >= RTK_FLOAT_MIN:
            return "float"
        return "single" if self.rtk_flag > 0 else "none"

    def sigma(self, dop_scale: float = 1.0) -> tuple[np.ndarray | None, str | None]:
        """(sigma east, north, height in metres, its source) by the first source of the
        module docstring's list that the image has; (None, None) without any."""
        if self.rtk_flag and self.rtk_std is not None and _positive(self.rtk_std):
            return np.maximum(self.rtk_std, MIN_RTK_SIGMA), "rtk"
        if _positive([self.gps_error]):
            return _from_horizontal(self.gps_error), "exif_error"
        if self.xmp_accuracy is not None and _positive(self.xmp_accuracy):
            xy, z = self.xmp_accuracy
            return np.array([xy, xy, z]), "xmp_accuracy"
        if _positive([self.gps_dop]):
            return _from_horizontal(self.gps_dop * dop_scale), "dop"
        return None, None

    def camera_key(self) -> tuple:
        """What tells cameras apart: make, model, serial number, focal length, image size."""
        focal = round(self.focal_length_mm, 2) if math.isfinite(self.focal_length_mm) else None
        return (self.make, self.model, self.serial, focal, self.width, self.height)

    def todict(self) -> dict:
        out = asdict(self)
        out["rtk_status"] = self.rtk_status
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in out.items()}


def _positive(values) -> bool:
    return all(v is not None and math.isfinite(v) and v > 0 for v in values)


def _from_horizontal(sigma_h: float) -> np.ndarray:
    return np.array([sigma_h, sigma_h, sigma_h * HEIGHT_TO_HORIZONTAL])


# -- reading --------------------------------------------------------------------------------------

def image_files(image_dir: str | Path) -> list[str]:
    """The image files below `image_dir` as COLMAP names them (paths relative to it, "/"
    separators), sorted; hidden files and folders left out. GNSSError for a missing folder
    or one without images."""
    from ..errors import GNSSError

    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise GNSSError("image directory does not exist", image_dir)
    names = sorted(p.relative_to(image_dir).as_posix() for p in image_dir.rglob("*")
                   if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
                   and not any(part.startswith(".") for part in p.relative_to(image_dir).parts))
    if not names:
        raise GNSSError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) found", image_dir)
    return names


def read_folder_metadata(image_dir: str | Path, names: list[str] | None = None,
                         progress: bool = True) -> list[ImageMetadata]:
    """The metadata of the images `names` (default: image_files) below `image_dir`; each
    image's warnings are logged."""
    from tqdm import tqdm

    image_dir = Path(image_dir)
    names = image_files(image_dir) if names is None else names
    out = []
    for name in tqdm(names, desc="image metadata", unit="img",
                     disable=not progress or len(names) < PROGRESS_MIN_IMAGES):
        meta = read_image_metadata(image_dir / name, name)
        for warning in meta.warnings:
            logger.warning("%s: %s", image_dir / name, warning)
        out.append(meta)
    return out


def read_image_metadata(path: str | Path, name: str | None = None) -> ImageMetadata:
    """The metadata of the image at `path` (`name`: how it is called in the block, default the
    file name). Never raises for a damaged or tagless file: its fields stay empty and
    `warnings` says why."""
    from PIL import ExifTags, Image, UnidentifiedImageError

    path = Path(path)
    meta = ImageMetadata(name=name if name is not None else path.name)
    limit = Image.MAX_IMAGE_PIXELS
    try:
        # The header only, never the pixels: no decompression bomb check (it would refuse the
        # header of a 280 MP aerial camera, or of a damaged one, with an exception).
        Image.MAX_IMAGE_PIXELS = None
        with warnings.catch_warnings(record=True) as caught:  # Pillow warns about damaged tags
            warnings.simplefilter("always")
            with Image.open(path) as image:
                meta.width, meta.height = image.size
                exif = image.getexif()
                gps = exif.get_ifd(ExifTags.IFD.GPSInfo) if exif else {}
                details = exif.get_ifd(ExifTags.IFD.Exif) if exif else {}
                packet = xmp_packet(image)
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as error:
        meta.warnings.append(f"cannot read the image header ({error})")
        return meta
    finally:
        Image.MAX_IMAGE_PIXELS = limit
    if caught:
        meta.warnings.append(f"damaged EXIF ({caught[0].message})")
    _camera_from_exif(meta, exif, details)
    _gps_from_exif(meta, {ExifTags.GPSTAGS.get(k, k): v for k, v in gps.items()})
    if packet:
        _from_xmp(meta, xmp_properties(packet, meta.warnings))
    return meta


def xmp_packet(image) -> bytes | None:
    """The raw XMP packet Pillow found in the file (JPEG and WebP APP1/chunk, PNG iTXt, TIFF
    tag 700), or None."""
    for key in ("xmp", "XML:com.adobe.xmp"):
        value = image.info.get(key)
        if value:
            return value.encode("utf-8") if isinstance(value, str) else bytes(value)
    tags = getattr(image, "tag_v2", None)
    value = tags.get(700) if tags is not None else None
    if value:
        return value.encode("utf-8") if isinstance(value, str) else bytes(value)
    return None


def xmp_properties(packet: bytes, problems: list[str] | None = None) -> dict[str, str]:
    """The simple properties of an XMP packet, "{namespace}name" -> text: the attributes of
    every rdf:Description and its child elements that hold text. A malformed packet is read as
    far as lxml's recovering parser gets (`problems` notes it)."""
    from lxml import etree

    parser = etree.XMLParser(recover=True, resolve_entities=False, no_network=True,
                             remove_comments=True)
    try:
        root = etree.fromstring(packet.strip(b"\0 \t\r\n"), parser)
    except etree.XMLSyntaxError as error:
        root = None
        detail = str(error)
    else:
        detail = "; ".join(str(e) for e in parser.error_log)[:200]
    if root is None:
        if problems is not None:
            problems.append(f"unreadable XMP ({detail or 'empty'})")
        return {}
    if detail and problems is not None:
        problems.append(f"damaged XMP, read as far as it goes ({detail})")
    out: dict[str, str] = {}
    for description in root.iter(f"{{{RDF_NAMESPACE}}}Description"):
        for key, value in description.attrib.items():
            if not key.startswith(f"{{{RDF_NAMESPACE}}}"):
                out.setdefault(key, value)
        for child in description:
            if isinstance(child.tag, str) and child.text and child.text.strip() and not len(child):
                out.setdefault(child.tag, child.text.strip())
    return out


# -- EXIF -----------------------------------------------------------------------------------------

def _rational(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return NAN


def _dms(value) -> float:
    if isinstance(value, (tuple, list)):
        parts = [_rational(v) for v in value] + [0.0, 0.0]
        return parts[0] + parts[1] / 60.0 + parts[2] / 3600.0
    return _rational(value)


def _text(value) -> str:
    if isinstance(value, bytes):
        value = value.decode("ascii", "ignore")
    return str(value).strip("\x00 ") if value is not None else ""


def _camera_from_exif(meta: ImageMetadata, exif, details) -> None:
    if not exif:
        return
    meta.make, meta.model = _text(exif.get(271)), _text(exif.get(272))  # Make, Model
    meta.serial = _text(details.get(0xA431) or exif.get(0xA431))  # BodySerialNumber
    meta.focal_length_mm = _rational(details.get(0x920A))  # FocalLength


def _gps_from_exif(meta: ImageMetadata, tags: dict) -> None:
    """Latitude, longitude, altitude and accuracy from the EXIF GPS tags (degrees, metres)."""
    if "GPSLatitude" in tags and "GPSLongitude" in tags:
        lat, lon = _dms(tags["GPSLatitude"]), _dms(tags["GPSLongitude"])
        if _text(tags.get("GPSLatitudeRef", "N")).upper() == "S":
            lat = -lat
        if _text(tags.get("GPSLongitudeRef", "E")).upper() == "W":
            lon = -lon
        if _valid_latlon(lat, lon):
            meta.latitude, meta.longitude, meta.position_source = lat, lon, "exif"
        else:
            meta.warnings.append(f"EXIF GPS position ({lat}, {lon}) is no position")
    altitude = _rational(tags.get("GPSAltitude", NAN))
    reference = tags.get("GPSAltitudeRef", 0)
    if isinstance(reference, bytes):
        reference = reference[0] if reference else 0
    if reference == 1:  # below sea level
        altitude = -altitude
    if math.isfinite(altitude):
        meta.altitude, meta.altitude_source = altitude, "exif"
    meta.gps_dop = _rational(tags.get("GPSDOP", NAN))
    meta.gps_error = _rational(tags.get("GPSHPositioningError", NAN))


def _valid_latlon(lat: float, lon: float) -> bool:
    """A position on the Earth, and not the (0, 0) that cameras without a fix write."""
    return (math.isfinite(lat) and math.isfinite(lon) and abs(lat) <= 90 and abs(lon) <= 180
            and not (lat == 0.0 and lon == 0.0))


# -- XMP ------------------------------------------------------------------------------------------

def _number(properties: dict, namespace: str, *names: str) -> float:
    """The first of `names` in `namespace` as a number ("+121.668", "1/2"), else NaN."""
    for name in names:
        text = properties.get(f"{{{namespace}}}{name}")
        if text is None:
            continue
        text = text.strip()
        try:
            if "/" in text:
                num, den = text.split("/", 1)
                return float(num) / float(den)
            return float(text)
        except (ValueError, ZeroDivisionError):
            return NAN
    return NAN


def _angles(properties: dict, namespace: str, prefix: str, suffix: str
            ) -> tuple[float, float, float] | None:
    values = tuple(_number(properties, namespace, f"{prefix}{axis}{suffix}")
                   for axis in ("Yaw", "Pitch", "Roll"))
    return values if all(math.isfinite(v) for v in values) else None


def _from_xmp(meta: ImageMetadata, p: dict) -> None:
    """DJI's and Pix4D's position, accuracy and attitude tags (module docstring)."""
    lat = _number(p, DJI_NAMESPACE, "GpsLatitude", "Latitude")
    lon = _number(p, DJI_NAMESPACE, "GpsLongitude", "GpsLongtitude", "Longitude")
    if _valid_latlon(lat, lon):
        meta.latitude, meta.longitude, meta.position_source = lat, lon, "xmp"
    altitude = _number(p, DJI_NAMESPACE, "AbsoluteAltitude")
    if math.isfinite(altitude):
        meta.altitude, meta.altitude_source = altitude, "xmp"
    meta.altitude_type = p.get(f"{{{DJI_NAMESPACE}}}AltitudeType")
    meta.relative_altitude = _number(p, DJI_NAMESPACE, "RelativeAltitude")
    flag = _number(p, DJI_NAMESPACE, "RtkFlag")
    if math.isfinite(flag):
        meta.rtk_flag = int(flag)
    std = tuple(_number(p, DJI_NAMESPACE, f"RtkStd{axis}") for axis in ("Lon", "Lat", "Hgt"))
    if all(math.isfinite(v) for v in std):
        meta.rtk_std = std
    accuracy = (_number(p, CAMERA_NAMESPACE, "GPSXYAccuracy"),
                _number(p, CAMERA_NAMESPACE, "GPSZAccuracy"))
    if all(math.isfinite(v) for v in accuracy):
        meta.xmp_accuracy = accuracy
    meta.gimbal = _angles(p, DJI_NAMESPACE, "Gimbal", "Degree")
    meta.flight = _angles(p, DJI_NAMESPACE, "Flight", "Degree")


# -- attitude -------------------------------------------------------------------------------------

def attitude_view(yaw: float, pitch: float) -> np.ndarray:
    """The unit viewing direction (east, north, up) of a camera whose gimbal points at `yaw`
    (degrees clockwise from north) and `pitch` (degrees, 0 level, -90 straight down): NED,
    rotation order ZYX, as DJI writes them. The roll turns the image about this direction."""
    y, p = np.radians(yaw), np.radians(pitch)
    return np.array([np.cos(p) * np.sin(y), np.cos(p) * np.cos(y), np.sin(p)])
