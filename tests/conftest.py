"""Fixtures shared by several test files."""

import pytest

from colmap_citymodel.synthetic_scene import StreetSceneOptions, make_street_scene


@pytest.fixture(scope="session")
def street_scene():
    """The synthetic street with known truth (seed 7): built once for every file that uses it.
    Tests copy what they change (refine copies its input reconstruction)."""
    return make_street_scene(StreetSceneOptions(seed=7))
