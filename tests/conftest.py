"""Fixtures shared by several test files."""

import numpy as np
import pytest

from colmap_citymodel.citymodel.build import store_from_polygons
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene


def box_store():
    """A 10 x 10 x 10 m box (walls and roof, no ground), local frame = CRS."""
    a = 10.0
    rings = [
        [(0, 0, 0), (a, 0, 0), (a, 0, a), (0, 0, a)],  # y = 0 wall, normal -y
        [(a, 0, 0), (a, a, 0), (a, a, a), (a, 0, a)],  # x = a wall, normal +x
        [(a, a, 0), (0, a, 0), (0, a, a), (a, a, a)],  # y = a wall, normal +y
        [(0, a, 0), (0, 0, 0), (0, 0, a), (0, a, a)],  # x = 0 wall, normal -x
        [(0, 0, a), (a, 0, a), (a, a, a), (0, a, a)],  # roof, normal +z
    ]
    return store_from_polygons([np.array(r, float) for r in rings], origin=np.zeros(3),
                               semantics=["WallSurface"] * 4 + ["RoofSurface"])


@pytest.fixture(scope="session")
def street_scene():
    """The synthetic street with known truth (seed 7): built once for every file that uses it.
    Tests copy what they change (refine copies its input reconstruction)."""
    return make_street_scene(StreetSceneOptions(seed=7))
