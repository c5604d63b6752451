"""CRS resolution (EPSG, OGC URN/URL, compound/versioned URNs, AdV URNs) and reprojection."""

from __future__ import annotations

import numpy as np
import pyproj
import pytest

from colmap_citymodel.citymodel.crs import ADV_CRS, lat_first, output_crs, reproject_points, resolve_crs, same_crs, user_crs
from colmap_citymodel.errors import CRSError


@pytest.mark.parametrize(
    "srs_name, horizontal, vertical",
    [
        ("EPSG:3946", 3946, None),
        ("EPSG::25832", 25832, None),
        ("25832", 25832, None),
        ("EPSG:25832+7837", 25832, 7837),
        ("urn:ogc:def:crs:EPSG::25832", 25832, None),
        ("urn:ogc:def:crs:EPSG::25833", 25833, None),
        ("urn:ogc:def:crs:EPSG:6.12:25833", 25833, None),
        ("urn:x-ogc:def:crs:EPSG:25832", 25832, None),
        ("http://www.opengis.net/def/crs/EPSG/0/25832", 25832, None),
        ("https://www.opengis.net/def/crs/EPSG/0/28992", 28992, None),
        ("urn:ogc:def:crs,crs:EPSG:6.12:25833,crs:EPSG:6.12:5783", 25833, 5783),
        ("urn:ogc:def:crs,crs:EPSG::25832,crs:EPSG::5783", 25832, 5783),
        (
            "http://www.opengis.net/def/crs-compound?1=http://www.opengis.net/def/crs/EPSG/0/25832"
            "&2=http://www.opengis.net/def/crs/EPSG/0/7837",
            25832,
            7837,
        ),
        ("urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH", 25832, 7837),
        ("urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH*GCG2016", 25832, 7837),
        ("urn:adv:crs:ETRS89_UTM33*DE_DHHN92_NH", 25833, 5783),
        ("urn:adv:crs:DE_DHDN_3GK4*DE_DHHN92_NH", 31468, 5783),
        ("urn:adv:crs:ETRS89_UTM32", 25832, None),
        ("EPSG:7415", 28992, 5709),  # a compound EPSG code is split into its parts
    ],
)
def test_resolve_projected(srs_name, horizontal, vertical):
    info = resolve_crs(srs_name)
    assert info.horizontal_epsg == horizontal
    assert info.vertical_epsg == vertical
    assert info.is_projected
    assert info.units == "metre"
    assert info.srs_name == srs_name
    # the WKT describes the same CRS (compound when a height system is named)
    crs = pyproj.CRS(info.wkt)
    assert crs.is_compound == (vertical is not None)
    sub = crs.sub_crs_list if crs.is_compound else [crs]
    assert sub[0].to_epsg() == horizontal
    if vertical:
        assert sub[1].to_epsg() == vertical


def test_adv_table_entries_are_what_their_names_say():
    """Each AdV name maps to an EPSG CRS whose name contains the same zone/height system."""
    expect = {
        "ETRS89_UTM32": "UTM zone 32N", "ETRS89_UTM33": "UTM zone 33N",
        "DE_DHDN_3GK2": "Gauss-Kruger zone 2", "DE_DHDN_3GK3": "Gauss-Kruger zone 3",
        "DE_DHDN_3GK4": "Gauss-Kruger zone 4", "DE_DHDN_3GK5": "Gauss-Kruger zone 5",
        "DE_DHHN2016_NH": "DHHN2016 height", "DE_DHHN92_NH": "DHHN92 height",
        "DE_DHHN85_NOH": "DHHN85 height",
    }
    for name, fragment in expect.items():
        assert fragment in pyproj.CRS.from_epsg(ADV_CRS[name]).name


@pytest.mark.parametrize(
    "srs_name, horizontal, vertical",
    [
        ("EPSG:6697", 6668, 6695),  # PLATEAU: JGD2011 + JGD2011 height
        ("http://www.opengis.net/def/crs/EPSG/0/6697", 6668, 6695),
        ("urn:ogc:def:crs:EPSG::4326", 4326, None),
        ("urn:adv:crs:ETRS89_Lat-Lon", 4258, None),
    ],
)
def test_resolve_geographic(srs_name, horizontal, vertical):
    info = resolve_crs(srs_name)
    assert not info.is_projected
    assert info.units == "degree"
    assert (info.horizontal_epsg, info.vertical_epsg) == (horizontal, vertical)


@pytest.mark.parametrize(
    "srs_name, fragment",
    [
        ("EPSG:999999", "unknown EPSG code"),
        ("urn:adv:crs:NOT_A_CRS*DE_DHHN92_NH", "unknown AdV CRS name"),
        ("this is no crs", "cannot interpret srsName"),
        ("EPSG:5783", "only a vertical CRS"),
        ("urn:ogc:def:crs,crs:EPSG::25832,crs:EPSG::25833", "two horizontal"),
    ],
)
def test_unknown_crs_names_file_and_string(srs_name, fragment):
    with pytest.raises(CRSError) as info:
        resolve_crs(srs_name, path="some/tile.gml")
    text = str(info.value)
    assert "some/tile.gml" in text
    assert srs_name in text
    assert fragment in text


def test_user_crs_and_same_crs():
    a = user_crs("EPSG:25832")
    b = resolve_crs("urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH")
    c = resolve_crs("urn:ogc:def:crs,crs:EPSG::25832,crs:EPSG::5783")
    assert same_crs(a, b) and same_crs(a, c)  # a missing height system matches any
    assert not same_crs(b, c)  # DHHN2016 vs DHHN92
    assert not same_crs(a, user_crs("EPSG:25833"))
    with pytest.raises(CRSError, match="--crs"):
        user_crs("EPSG:0")


def test_reproject_geographic_lat_lon_order():
    """PLATEAU stores latitude, longitude, height; the result is easting, northing, height."""
    src = resolve_crs("EPSG:6697")
    dst = user_crs("EPSG:6677")
    lat, lon, h = 35.67894842882243, 139.71765053158802, 50.534
    out = reproject_points(np.array([[lat, lon, h]]), src, dst)
    # independent: pyproj with the CRSs' own axis order (6677 is northing, easting)
    t = pyproj.Transformer.from_crs("EPSG:6668", "EPSG:6677")
    north, east = t.transform(lat, lon)
    np.testing.assert_allclose(out[0], [east, north, h], atol=1e-6)
    # Japan plane rectangular CS IX has its origin at 36N 139d50'E: the point lies ~35.6 km
    # south and ~10.4 km west of it
    assert -36_000 < out[0, 1] < -35_000 and -11_000 < out[0, 0] < -10_000
    # heights pass through and the output keeps the height system
    out_crs = output_crs(src, dst)
    assert (out_crs.horizontal_epsg, out_crs.vertical_epsg) == (6677, 6695)


def test_reproject_detects_lon_lat_files():
    src = resolve_crs("EPSG:4326")
    pts_latlon = np.array([[52.0, 13.0, 0.0], [52.1, 13.1, 0.0]])
    pts_lonlat = pts_latlon[:, [1, 0, 2]]
    # 13 < 90: a lon-lat file is only recognisable when a longitude exceeds 90; force it here
    assert lat_first(pts_latlon, src)
    dst = user_crs("EPSG:25833")
    a = reproject_points(pts_latlon, src, dst)
    b = reproject_points(pts_lonlat, src, dst, swap_lat_lon=False)
    np.testing.assert_allclose(a, b, atol=1e-6)
    assert 350_000 < a[0, 0] < 450_000 and 5_700_000 < a[0, 1] < 5_800_000
    far_east = np.array([[139.7, 35.6, 0.0]])  # longitude first: first value > 90
    assert not lat_first(far_east, src)


def test_reproject_projected_to_projected_roundtrip():
    src = user_crs("EPSG:25832")
    dst = user_crs("EPSG:25833")
    pts = np.array([[690930.0, 5335940.0, 520.0], [691050.0, 5336100.0, 530.0]])
    there = reproject_points(pts, src, dst)
    back = reproject_points(there, dst, src)
    np.testing.assert_allclose(back, pts, atol=1e-6)
    # distances are nearly preserved (scale differs by far less than 1e-3 between zones)
    d0 = np.linalg.norm(pts[1] - pts[0])
    d1 = np.linalg.norm(there[1] - there[0])
    assert abs(d1 / d0 - 1) < 2e-3
