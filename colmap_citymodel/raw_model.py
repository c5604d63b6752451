"""Plain data that every city model reader returns, before vertices are merged into a store.

Readers (read_citygml.py, read_cityjson.py) produce a `RawCityModel`; plane_store.build_store()
turns it into a `PlaneStore`. Coordinates here are still in the file's CRS (or the target CRS
when the reader reprojected), float64, never shifted.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class CRSInfo:
    """A resolved coordinate reference system of a city model."""

    srs_name: str | None  # as written in the file (or given by the user)
    horizontal_epsg: int | None  # e.g. 25832
    vertical_epsg: int | None  # e.g. 7837 (DHHN2016 height); None when unknown/absent
    wkt: str  # WKT2 of the (compound) CRS
    is_projected: bool
    units: str = "metre"

    @property
    def label(self) -> str:
        if self.horizontal_epsg and self.vertical_epsg:
            return f"EPSG:{self.horizontal_epsg}+{self.vertical_epsg}"
        if self.horizontal_epsg:
            return f"EPSG:{self.horizontal_epsg}"
        return self.srs_name or "unknown"


@dataclass(slots=True)
class RawPolygon:
    """One planar surface polygon as read from a file (slots: a city has 1e5-1e6 of them)."""

    exterior: np.ndarray  # (N, 3) float64, ring without the repeated closing point
    holes: list[np.ndarray] = field(default_factory=list)  # each (M, 3) float64
    semantic: str = "Unknown"  # WallSurface, RoofSurface, GroundSurface, ClosureSurface, ...
    building_id: str = ""
    part_id: str = ""  # BuildingPart id, "" when the polygon belongs to the building itself
    gml_id: str = ""  # the polygon's own id ("" when it has none)
    lod: int = 2
    from_solid: bool = False  # True when the polygon is a face of a closed solid (outward order)


@dataclass
class RawCityModel:
    source: str  # file path(s) it was read from
    format: str  # "CityGML" or "CityJSON"
    version: str  # "1.0", "2.0", "3.0", "1.1", ...
    crs: CRSInfo
    polygons: list[RawPolygon]
    building_ids: list[str]
    part_ids: list[str]
    warnings: list[str] = field(default_factory=list)
