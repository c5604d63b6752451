"""The synthetic street's SfM input: its drift is a rate per metre of street."""

import numpy as np
import pytest

from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene


def helmert_residuals(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Residuals (target minus fit) of the 7-parameter similarity source -> target."""
    a, b = source - source.mean(0), target - target.mean(0)
    u, s, vt = np.linalg.svd(b.T @ a)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ d @ vt
    scale = np.trace(np.diag(s) @ d) / (a ** 2).sum()
    return b - scale * a @ rotation.T


def sfm_bend(num_stations: int, drift: float) -> tuple[float, float]:
    """(largest deformation of the SfM camera centres after a Helmert fit to the truth, m;
    the street's length, m)."""
    options = StreetSceneOptions(num_stations=num_stations, point_spacing=4.0, seed=2,
                                 drift=drift)
    scene = make_street_scene(options)
    true = {im.name: im.projection_center() for im in scene.truth.images.values()}
    names = sorted(true)
    sfm = {im.name: im.projection_center() for im in scene.sfm.images.values()}
    residuals = helmert_residuals(np.array([sfm[n] for n in names]),
                                  np.array([true[n] for n in names]))
    return float(np.linalg.norm(residuals, axis=1).max()), \
        options.num_stations * options.station_spacing


@pytest.mark.parametrize("drift", [0.01, 0.03])
def test_the_sfm_bend_is_the_same_fraction_of_a_short_and_a_long_street(drift):
    short, short_length = sfm_bend(20, drift)
    long, long_length = sfm_bend(160, drift)
    # A parabola over the street keeps 1/6 of its rise after the best straight line.
    for bend, length in ((short, short_length), (long, long_length)):
        assert bend / length == pytest.approx(drift / 6, rel=0.2)
    assert long / long_length == pytest.approx(short / short_length, rel=0.15)
    assert long > 6 * short  # eight times the length: eight times the bend, not 64


def test_without_drift_the_sfm_input_is_a_similarity_of_the_truth():
    bend, _ = sfm_bend(20, 0.0)
    assert bend < 1e-6
