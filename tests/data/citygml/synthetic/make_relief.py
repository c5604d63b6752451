"""Writes `relief_tin_house.gml` of this folder (run from anywhere:
`python tests/data/citygml/synthetic/make_relief.py`; the output is deterministic).

CityGML 2.0, EPSG:25832+7837 on the envelope: one flat-roofed Building (10 x 8 m, 6 m high)
and one `dem:ReliefFeature` whose `dem:TINRelief` is a 60 x 60 m sloped plane around it, as
72 `gml:Triangle`s on a 10 m grid with heights z = 100 + 0.03 (x - X0) + 0.01 (y - Y0): the
building stands on the relief at the height of its centre.
"""

from __future__ import annotations

from pathlib import Path

HERE = Path(__file__).resolve().parent
X0, Y0 = 691000.0, 5335000.0


def relief_height(x: float, y: float) -> float:
    return 100.0 + 0.03 * (x - X0) + 0.01 * (y - Y0)


def _ring(points) -> str:
    closed = list(points) + [points[0]]
    return " ".join(f"{x:.3f} {y:.3f} {z:.3f}" for x, y, z in closed)


def _polygon(points) -> str:
    return ("<gml:Polygon><gml:exterior><gml:LinearRing><gml:posList>"
            f"{_ring(points)}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon>")


def _building() -> str:
    x0, y0, x1, y1 = X0 + 25, Y0 + 26, X0 + 35, Y0 + 34
    z0 = relief_height(X0 + 30, Y0 + 30)
    h = z0 + 6.0
    p = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    surfaces = [("GroundSurface", [(x, y, z0) for x, y in reversed(p)]),
                ("RoofSurface", [(x, y, h) for x, y in p])]
    for (ax, ay), (bx, by) in zip(p, p[1:] + p[:1]):
        surfaces.append(("WallSurface", [(ax, ay, z0), (bx, by, z0), (bx, by, h), (ax, ay, h)]))
    parts = [f"<bldg:boundedBy><bldg:{kind}><bldg:lod2MultiSurface><gml:MultiSurface>"
             f"<gml:surfaceMember>{_polygon(ring)}</gml:surfaceMember></gml:MultiSurface>"
             f"</bldg:lod2MultiSurface></bldg:{kind}></bldg:boundedBy>"
             for kind, ring in surfaces]
    return ('<core:cityObjectMember><bldg:Building gml:id="house">'
            + "".join(parts) + "</bldg:Building></core:cityObjectMember>")


def _relief() -> str:
    triangles = []
    for i in range(6):
        for j in range(6):
            a, b = (X0 + 10 * i, Y0 + 10 * j), (X0 + 10 * i + 10, Y0 + 10 * j)
            c, d = (X0 + 10 * i + 10, Y0 + 10 * j + 10), (X0 + 10 * i, Y0 + 10 * j + 10)
            for tri in ((a, b, c), (a, c, d)):
                pts = [(x, y, relief_height(x, y)) for x, y in tri]
                triangles.append("<gml:Triangle><gml:exterior><gml:LinearRing><gml:posList>"
                                 f"{_ring(pts)}</gml:posList></gml:LinearRing></gml:exterior>"
                                 "</gml:Triangle>")
    return ('<core:cityObjectMember><dem:ReliefFeature gml:id="relief"><dem:lod>2</dem:lod>'
            '<dem:reliefComponent><dem:TINRelief gml:id="tin"><dem:lod>2</dem:lod><dem:tin>'
            "<gml:TriangulatedSurface><gml:trianglePatches>" + "".join(triangles)
            + "</gml:trianglePatches></gml:TriangulatedSurface></dem:tin></dem:TINRelief>"
            "</dem:reliefComponent></dem:ReliefFeature></core:cityObjectMember>")


def main() -> None:
    text = (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" '
        'xmlns:bldg="http://www.opengis.net/citygml/building/2.0" '
        'xmlns:dem="http://www.opengis.net/citygml/relief/2.0" '
        'xmlns:gml="http://www.opengis.net/gml">\n'
        '<gml:boundedBy><gml:Envelope srsName="EPSG:25832+7837" srsDimension="3">'
        f"<gml:lowerCorner>{X0:.3f} {Y0:.3f} 90.000</gml:lowerCorner>"
        f"<gml:upperCorner>{X0 + 60:.3f} {Y0 + 60:.3f} 120.000</gml:upperCorner>"
        "</gml:Envelope></gml:boundedBy>\n"
        + _building() + "\n" + _relief() + "\n</core:CityModel>\n")
    (HERE / "relief_tin_house.gml").write_text(text)


if __name__ == "__main__":
    main()
