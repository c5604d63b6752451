"""Writes the two synthetic CityGML files of this folder (run from anywhere:
`python tests/data/citygml/synthetic/make_synthetic.py`; the output is deterministic).

- `parts_xlinked_solids_v1.gml`: CityGML 1.0, EPSG:28992 named only on the top-level envelope,
  one Building made of three BuildingParts (two flat-roofed boxes and a gabled part, touching
  each other), coordinates as `gml:pos` only, every part's `lod2Solid` built from `xlink:href`
  references to the polygons of its thematic surfaces. 19 polygons: 12 walls, 4 roofs, 3 grounds.
- `no_crs_house_part.gml`: CityGML 2.0 with no `srsName` anywhere (the coordinates are
  EPSG:3946, around Lyon), a wrong `core` namespace (`.../citygml/base/2.0`), `srsDimension`
  only on the envelopes and multi-surfaces (`gml:posList` without it), one Building whose
  geometry is one BuildingPart: a gabled house, 7 polygons (4 walls, 2 roofs, 1 ground), its
  `lod2Solid` made of references.

Each solid is closed and its polygons face outwards (counter-clockwise seen from outside).
"""

from __future__ import annotations

import math
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _box(x0, y0, x1, y1, z0, h):
    """Flat-roofed box: (semantic, ring) with outward counter-clockwise rings."""
    p = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    out = [("GroundSurface", [(x, y, z0) for x, y in reversed(p)])]
    for (ax, ay), (bx, by) in zip(p, p[1:] + p[:1]):
        out.append(("WallSurface", [(ax, ay, z0), (bx, by, z0), (bx, by, z0 + h), (ax, ay, z0 + h)]))
    out.append(("RoofSurface", [(x, y, z0 + h) for x, y in p]))
    return out


def _gable(corners, z0, eaves, ridge):
    """Gabled part on the footprint p0 p1 p2 p3 (counter-clockwise from above); the ridge runs
    parallel to p0 -> p1, midway between p0 p1 and p3 p2."""
    p0, p1, p2, p3 = corners
    mid = lambda a, b: ((a[0] + b[0]) / 2, (a[1] + b[1]) / 2)  # noqa: E731
    r1, r0 = mid(p1, p2), mid(p0, p3)
    ze, zr = z0 + eaves, z0 + ridge
    b = lambda q: (q[0], q[1], z0)  # noqa: E731
    e = lambda q: (q[0], q[1], ze)  # noqa: E731
    t = lambda q: (q[0], q[1], zr)  # noqa: E731
    return [
        ("GroundSurface", [b(p3), b(p2), b(p1), b(p0)]),
        ("WallSurface", [b(p0), b(p1), e(p1), e(p0)]),
        ("WallSurface", [b(p1), b(p2), e(p2), t(r1), e(p1)]),
        ("WallSurface", [b(p2), b(p3), e(p3), e(p2)]),
        ("WallSurface", [b(p3), b(p0), e(p0), t(r0), e(p3)]),
        ("RoofSurface", [e(p0), e(p1), t(r1), t(r0)]),
        ("RoofSurface", [e(p2), e(p3), t(r0), t(r1)]),
    ]


def _fmt(v: float) -> str:
    return f"{v:.3f}"


def _parts_xlinked_solids() -> str:
    ox, oy, oz = 78600.0, 457900.0, 3.0
    parts = {
        "A": _box(0.0, 0.0, 10.0, 8.0, 0.0, 9.0),
        "B": _box(10.0, 0.0, 16.0, 8.0, 0.0, 6.0),
        "C": _gable([(-8.0, 0.0), (0.0, 0.0), (0.0, 8.0), (-8.0, 8.0)], 0.0, 6.0, 9.0),
    }
    xs = [ox + x for faces in parts.values() for _, ring in faces for x, _, _ in ring]
    ys = [oy + y for faces in parts.values() for _, ring in faces for _, y, _ in ring]
    zs = [oz + z for faces in parts.values() for _, ring in faces for _, _, z in ring]
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        "<!-- Synthetic test data written by tests/data/citygml/synthetic/make_synthetic.py -->",
        '<CityModel xmlns="http://www.opengis.net/citygml/1.0"',
        '  xmlns:bldg="http://www.opengis.net/citygml/building/1.0"',
        '  xmlns:gml="http://www.opengis.net/gml"',
        '  xmlns:xlink="http://www.w3.org/1999/xlink">',
        "  <gml:name>one building of three parts</gml:name>",
        "  <gml:boundedBy>",
        '    <gml:Envelope srsName="urn:ogc:def:crs:EPSG::28992">',
        f"      <gml:lowerCorner>{_fmt(min(xs))} {_fmt(min(ys))} {_fmt(min(zs))}</gml:lowerCorner>",
        f"      <gml:upperCorner>{_fmt(max(xs))} {_fmt(max(ys))} {_fmt(max(zs))}</gml:upperCorner>",
        "    </gml:Envelope>",
        "  </gml:boundedBy>",
        "  <cityObjectMember>",
        '    <bldg:Building gml:id="SYN_B1">',
    ]
    for name, faces in parts.items():
        pid = f"SYN_B1_{name}"
        ids = [f"{pid}_{i + 1}" for i in range(len(faces))]
        out += [
            "      <bldg:consistsOfBuildingPart>",
            f'        <bldg:BuildingPart gml:id="{pid}">',
        ]
        out += _xlinked_solid(ids)
        for (semantic, ring), gid in zip(faces, ids):
            positions = [f"                          <gml:pos>{_fmt(ox + x)} {_fmt(oy + y)} "
                         f"{_fmt(oz + z)}</gml:pos>" for x, y, z in ring + ring[:1]]
            out += _bounded_by(semantic, gid, positions, "<gml:MultiSurface>")
        out += ["        </bldg:BuildingPart>", "      </bldg:consistsOfBuildingPart>"]
    out += ["    </bldg:Building>", "  </cityObjectMember>", "</CityModel>", ""]
    return "\n".join(out)


def _xlinked_solid(ids: list[str]) -> list[str]:
    """A part's lod2Solid whose surfaces are xlinks to its boundary polygons `ids`."""
    return [
        "          <bldg:lod2Solid>",
        "            <gml:Solid>",
        "              <gml:exterior>",
        "                <gml:CompositeSurface>",
        *[f'                  <gml:surfaceMember xlink:href="#{i}"/>' for i in ids],
        "                </gml:CompositeSurface>",
        "              </gml:exterior>",
        "            </gml:Solid>",
        "          </bldg:lod2Solid>",
    ]


def _bounded_by(semantic: str, gid: str, ring_lines: list[str], multi_surface: str
                ) -> list[str]:
    """One thematic surface holding polygon `gid`, its exterior ring given as `ring_lines`."""
    return [
        "          <bldg:boundedBy>",
        f"            <bldg:{semantic}>",
        "              <bldg:lod2MultiSurface>",
        f"                {multi_surface}",
        "                  <gml:surfaceMember>",
        f'                    <gml:Polygon gml:id="{gid}">',
        "                      <gml:exterior>",
        "                        <gml:LinearRing>",
        *ring_lines,
        "                        </gml:LinearRing>",
        "                      </gml:exterior>",
        "                    </gml:Polygon>",
        "                  </gml:surfaceMember>",
        "                </gml:MultiSurface>",
        "              </bldg:lod2MultiSurface>",
        f"            </bldg:{semantic}>",
        "          </bldg:boundedBy>",
    ]


def _no_crs_house_part() -> str:
    ox, oy, oz = 1841515.0, 5175885.0, 197.4
    a = math.radians(17.0)
    c, s = math.cos(a), math.sin(a)
    rot = lambda x, y: (round(ox + c * x - s * y, 3), round(oy + s * x + c * y, 3))  # noqa: E731
    corners = [rot(0.0, 0.0), rot(13.8, 0.0), rot(13.8, 6.4), rot(0.0, 6.4)]
    faces = _gable(corners, 0.0, 8.5, 10.4)
    ids = [f"SYN_H1_1_poly{i + 1}" for i in range(len(faces))]
    pts = [(x, y, oz + z) for _, ring in faces for x, y, z in ring]
    lo = [min(q[k] for q in pts) for k in range(3)]
    hi = [max(q[k] for q in pts) for k in range(3)]
    out = [
        '<?xml version="1.0" encoding="UTF-8" standalone="no" ?>',
        "<!-- Synthetic test data written by tests/data/citygml/synthetic/make_synthetic.py -->",
        '<CityModel xmlns="http://www.opengis.net/citygml/2.0"',
        '  xmlns:bldg="http://www.opengis.net/citygml/building/2.0"',
        '  xmlns:core="http://www.opengis.net/citygml/base/2.0"',
        '  xmlns:gml="http://www.opengis.net/gml"',
        '  xmlns:xlink="http://www.w3.org/1999/xlink">',
        "  <gml:name>a house without a CRS</gml:name>",
        "  <gml:boundedBy>",
        '    <gml:Envelope srsDimension="3">',
        f"      <gml:lowerCorner>{_fmt(lo[0])} {_fmt(lo[1])} {_fmt(lo[2])}</gml:lowerCorner>",
        f"      <gml:upperCorner>{_fmt(hi[0])} {_fmt(hi[1])} {_fmt(hi[2])}</gml:upperCorner>",
        "    </gml:Envelope>",
        "  </gml:boundedBy>",
        "  <cityObjectMember>",
        '    <bldg:Building gml:id="SYN_H1">',
        "      <creationDate>2017-04-05</creationDate>",
        "      <bldg:consistsOfBuildingPart>",
        '        <bldg:BuildingPart gml:id="SYN_H1_1">',
        '          <bldg:measuredHeight uom="#m">10.400</bldg:measuredHeight>',
    ]
    out += _xlinked_solid(ids)
    for (semantic, ring), gid in zip(faces, ids):
        coords = " ".join(f"{_fmt(x)} {_fmt(y)} {_fmt(oz + z)}" for x, y, z in ring + ring[:1])
        out += _bounded_by(semantic, gid,
                           [f"                          <gml:posList>{coords}</gml:posList>"],
                           '<gml:MultiSurface srsDimension="3">')
    out += [
        "        </bldg:BuildingPart>",
        "      </bldg:consistsOfBuildingPart>",
        "    </bldg:Building>",
        "  </cityObjectMember>",
        "</CityModel>",
        "",
    ]
    return "\n".join(out)


def main() -> None:
    (HERE / "parts_xlinked_solids_v1.gml").write_text(_parts_xlinked_solids())
    (HERE / "no_crs_house_part.gml").write_text(_no_crs_house_part())


if __name__ == "__main__":
    main()
