"""Fixtures shared by several test files."""

import hashlib
from pathlib import Path

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


@pytest.fixture(scope="session")
def street_refined(street_scene):
    """`refine` of the synthetic street with the default options, as the package API runs it:
    built once for every file that checks what a default refine gives. Shared: read it, never
    change it (copy what a test changes)."""
    import colmap_citymodel

    return colmap_citymodel.refine(street_scene.sfm, street_scene.store, street_scene.gnss(),
                                   colmap_citymodel.RefineOptions(), progress=False)


#: Where slow simulated inputs are kept between test runs (git-ignored, like every build/).
TEST_CACHE = Path(__file__).resolve().parents[1] / "build" / "test-cache"


def simulator_version() -> str:
    """A hash of the simulator's code (colmap_citymodel/simulate) and of pycolmap's version,
    whose mapper builds the sequences: a change to either builds them anew."""
    import pycolmap

    from colmap_citymodel import simulate

    digest = hashlib.sha256(pycolmap.__version__.encode())
    for path in sorted(Path(simulate.__file__).parent.glob("*.py")):
        digest.update(path.name.encode() + path.read_bytes())
    return digest.hexdigest()[:12]


@pytest.fixture(scope="session")
def sequence_cache() -> Path:
    """The `cache_path` of simulate.sequence.main for tests: a simulated, COLMAP-mapped
    sequence is built once, keyed by its options (simulate.scenario.sequence_key) under the
    simulator's code version, and every workspace derived from it by copying. Builds appear by
    one rename, so parallel test runs share them safely."""
    return TEST_CACHE / f"sequences-{simulator_version()}"
