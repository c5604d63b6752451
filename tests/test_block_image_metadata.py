"""EXIF and XMP of photographs: small JPEGs written here with EXIF GPS (Pillow) and a DJI XMP
packet inserted as its own APP1 segment, as DJI's cameras write it; positions, RTK sigmas,
attitude, missing and damaged tags, and the GNSS they give in a projected CRS. One real photo
from tests/data (Lund) for a phone's tags."""

from __future__ import annotations

import struct

import numpy as np
import pyproj
import pytest
from PIL import ExifTags, Image

from colmap_citymodel.block.gnss import read_gnss_exif
from colmap_citymodel.block.image_metadata import (MIN_RTK_SIGMA, attitude_view, image_files,
                                                   read_folder_metadata, read_image_metadata,
                                                   xmp_properties)
from colmap_citymodel.citymodel.crs import user_crs
from colmap_citymodel.errors import GNSSError
from data_paths import LUND

UTM32 = user_crs("EPSG:25832")
XMP_HEADER = b"http://ns.adobe.com/xap/1.0/\x00"


def dji_xmp(**tags) -> bytes:
    """An XMP packet as DJI writes it: the drone-dji tags as attributes of rdf:Description."""
    attributes = "\n".join(f'   drone-dji:{k}="{v}"' for k, v in tags.items())
    return (
        "<?xpacket begin='\ufeff' id='W5M0MpCehiHzreSzNTczkc9d'?>\n"
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
        ' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
        '  <rdf:Description rdf:about="DJI Meta Data"\n'
        '    xmlns:tiff="http://ns.adobe.com/tiff/1.0/"\n'
        '    xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"\n'
        f'   tiff:Make="DJI"\n{attributes}>\n'
        "  </rdf:Description>\n </rdf:RDF>\n</x:xmpmeta>\n<?xpacket end='w'?>"
    ).encode("utf-8")


def dms(value: float):
    degrees = int(value)
    minutes = int((value - degrees) * 60)
    return (float(degrees), float(minutes), (value - degrees - minutes / 60) * 3600)


def write_jpeg(path, *, gps: dict | None = None, xmp: bytes | None = None, make="DJI",
               model="M3E", size=(64, 48)):
    """A small JPEG with EXIF (make, model, focal length, `gps` tags by name) and the XMP
    packet inserted as its own APP1 segment."""
    exif = Image.Exif()
    exif[ExifTags.Base.Make], exif[ExifTags.Base.Model] = make, model
    exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLength] = 12.29
    if gps:
        ifd = exif.get_ifd(ExifTags.IFD.GPSInfo)
        codes = {name: code for code, name in ExifTags.GPSTAGS.items()}
        for name, value in gps.items():
            ifd[codes[name]] = value
    Image.new("RGB", size, (90, 120, 150)).save(path, exif=exif, quality=80)
    if xmp is not None:
        data = path.read_bytes()
        segment = XMP_HEADER + xmp
        app1 = b"\xff\xe1" + struct.pack(">H", len(segment) + 2) + segment
        assert data[:2] == b"\xff\xd8"  # SOI: the XMP segment follows it
        path.write_bytes(data[:2] + app1 + data[2:])
    return path


def exif_gps(lat, lon, alt, **more):
    return {"GPSLatitudeRef": "N" if lat >= 0 else "S", "GPSLatitude": dms(abs(lat)),
            "GPSLongitudeRef": "E" if lon >= 0 else "W", "GPSLongitude": dms(abs(lon)),
            "GPSAltitudeRef": b"\x00", "GPSAltitude": float(alt), **more}


RTK_FIXED = dict(GpsLatitude="51.4627318512", GpsLongitude="+7.0135674231",
                 AbsoluteAltitude="+171.668", RelativeAltitude="+109.983", AltitudeType="RtkAlt",
                 GimbalRollDegree="+0.00", GimbalYawDegree="-124.40", GimbalPitchDegree="-89.90",
                 FlightRollDegree="+7.10", FlightYawDegree="-123.00", FlightPitchDegree="+2.30",
                 RtkFlag="50", RtkStdLon="0.01234", RtkStdLat="0.00800", RtkStdHgt="0.02100")


def test_dji_rtk_fixed(tmp_path):
    path = write_jpeg(tmp_path / "DJI_0001.JPG", gps=exif_gps(51.46273, 7.01356, 171.0),
                      xmp=dji_xmp(**RTK_FIXED))
    meta = read_image_metadata(path)
    assert not meta.warnings
    # the XMP's position and absolute altitude win over the EXIF GPS (fewer decimals)
    assert (meta.latitude, meta.longitude, meta.altitude) == (51.4627318512, 7.0135674231,
                                                              171.668)
    assert meta.position_source == meta.altitude_source == "xmp"
    assert meta.altitude_type == "RtkAlt" and meta.relative_altitude == pytest.approx(109.983)
    assert meta.rtk_status == "fixed"
    sigma, source = meta.sigma()
    assert source == "rtk"
    np.testing.assert_allclose(sigma, [0.01234, MIN_RTK_SIGMA[1], 0.021])  # lat 8 mm: floor
    assert meta.gimbal == (-124.4, -89.9, 0.0) and meta.flight == (-123.0, 2.3, 7.1)
    assert (meta.make, meta.model, meta.width, meta.height) == ("DJI", "M3E", 64, 48)
    assert meta.focal_length_mm == pytest.approx(12.29)


def test_rtk_float_single_and_none(tmp_path):
    float_ = write_jpeg(tmp_path / "a.jpg", xmp=dji_xmp(
        **{**RTK_FIXED, "RtkFlag": "34", "RtkStdLon": "0.31", "RtkStdLat": "0.28",
           "RtkStdHgt": "0.52"}))
    meta = read_image_metadata(float_)
    assert meta.rtk_status == "float"
    np.testing.assert_allclose(meta.sigma()[0], [0.31, 0.28, 0.52])
    single = read_image_metadata(write_jpeg(tmp_path / "b.jpg", xmp=dji_xmp(
        **{**RTK_FIXED, "RtkFlag": "16", "RtkStdLon": "1.5", "RtkStdLat": "1.4",
           "RtkStdHgt": "2.9"})))
    assert single.rtk_status == "single" and single.sigma()[1] == "rtk"
    # no RTK position (flag 0, zero deviations): the EXIF accuracy, here GPSDOP in metres
    none = read_image_metadata(write_jpeg(
        tmp_path / "c.jpg", gps=exif_gps(51.46, 7.01, 170.0, GPSDOP=2.5),
        xmp=dji_xmp(**{**RTK_FIXED, "RtkFlag": "0", "RtkStdLon": "0", "RtkStdLat": "0",
                       "RtkStdHgt": "0"})))
    assert none.rtk_status == "none"
    sigma, source = none.sigma()
    assert source == "dop"
    np.testing.assert_allclose(sigma, [2.5, 2.5, 2.5 * 5 / 3])


def test_exif_only_and_missing_tags(tmp_path):
    phone = read_image_metadata(write_jpeg(
        tmp_path / "phone.jpg", make="Apple", model="iPhone 12",
        gps=exif_gps(-33.8568, -151.2153, 12.0, GPSHPositioningError=4.0)))
    assert phone.position_source == "exif" and phone.rtk_status is None and phone.gimbal is None
    assert phone.latitude == pytest.approx(-33.8568) and phone.longitude == pytest.approx(-151.2153)
    sigma, source = phone.sigma()
    assert source == "exif_error"
    np.testing.assert_allclose(sigma, [4.0, 4.0, 4.0 * 5 / 3])
    bare = read_image_metadata(write_jpeg(tmp_path / "bare.jpg"))
    assert not bare.has_position and bare.sigma() == (None, None)
    no_altitude = exif_gps(48.1, 11.5, 0.0)
    del no_altitude["GPSAltitude"], no_altitude["GPSAltitudeRef"]
    flat = read_image_metadata(write_jpeg(tmp_path / "flat.jpg", gps=no_altitude))
    assert flat.latitude == pytest.approx(48.1) and not flat.has_position
    zero = read_image_metadata(write_jpeg(tmp_path / "zero.jpg", gps=exif_gps(0.0, 0.0, 5.0)))
    assert not zero.has_position and "no position" in zero.warnings[0]
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"\xff\xd8\xff\xe1\x00\x10garbage")
    assert "cannot read the image header" in read_image_metadata(broken).warnings[0]


def test_damaged_xmp_and_other_spellings(tmp_path):
    cut = dji_xmp(**RTK_FIXED)[:-120]  # the packet's end is missing
    meta = read_image_metadata(write_jpeg(tmp_path / "cut.jpg",
                                          gps=exif_gps(51.46, 7.01, 170.0), xmp=cut))
    assert meta.rtk_flag == 50 and any("damaged XMP" in w for w in meta.warnings)
    elements = (b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/'
                b'02/22-rdf-syntax-ns#"><rdf:Description xmlns:drone-dji="http://www.dji.com/'
                b'drone-dji/1.0/"><drone-dji:GpsLatitude>47.25</drone-dji:GpsLatitude>'
                b"<drone-dji:GpsLongtitude>8.5</drone-dji:GpsLongtitude>"
                b"<drone-dji:AbsoluteAltitude>500.5</drone-dji:AbsoluteAltitude>"
                b"</rdf:Description></rdf:RDF></x:xmpmeta>")
    old = read_image_metadata(write_jpeg(tmp_path / "old.jpg", xmp=elements))
    assert (old.latitude, old.longitude, old.altitude) == (47.25, 8.5, 500.5)
    assert xmp_properties(b"<not xml") == {}


def test_gnss_from_a_folder_of_drone_photos(tmp_path):
    lats = [51.46273, 51.46280, 51.46290]
    for k, lat in enumerate(lats):
        write_jpeg(tmp_path / f"DJI_{k:04d}.JPG", xmp=dji_xmp(
            **{**RTK_FIXED, "GpsLatitude": f"{lat}", "RtkFlag": "50" if k else "34",
               "RtkStdLon": "0.02" if k else "0.4"}))
    (tmp_path / "sub").mkdir()
    write_jpeg(tmp_path / "sub" / "x.jpg")  # no position: left out
    assert image_files(tmp_path) == ["DJI_0000.JPG", "DJI_0001.JPG", "DJI_0002.JPG",
                                     "sub/x.jpg"]
    gnss = read_gnss_exif(tmp_path, UTM32, default_sigma=(3.0, 3.0, 5.0))
    assert gnss.image_names == ["DJI_0000.JPG", "DJI_0001.JPG", "DJI_0002.JPG"]
    to_utm = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:25832", always_xy=True)
    for k, lat in enumerate(lats):
        east, north = to_utm.transform(7.0135674231, lat)
        np.testing.assert_allclose(gnss.positions[k], [east, north, 171.668], atol=1e-6)
    np.testing.assert_allclose(gnss.sigmas[0], [0.4, 0.01, 0.021])
    np.testing.assert_allclose(gnss.sigmas[1], [0.02, 0.01, 0.021])
    assert "3 from RTK standard deviations" in gnss.notes[-1]
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no photos")
    with pytest.raises(GNSSError, match="no images"):
        read_gnss_exif(empty, UTM32)


def test_phone_photo_and_attitude_view():
    meta = read_folder_metadata(LUND, ["01.jpg"])[0]
    # an iPhone 4S whose EXIF names no make; its focal length (4.3 mm) tells the camera
    assert meta.make == "" and meta.focal_length_mm == pytest.approx(4.3)
    assert meta.position_source == "exif" and meta.rtk_status is None
    assert (meta.width, meta.height) == (1024, 768) and meta.sigma()[1] == "dop"
    np.testing.assert_allclose(attitude_view(0.0, -90.0), [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(attitude_view(90.0, 0.0), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(attitude_view(-135.0, -45.0), [-0.5, -0.5, -np.sqrt(0.5)],
                               atol=1e-12)
