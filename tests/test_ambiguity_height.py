"""The height test of the verdict (precision.ambiguity.height_fit): with the GNSS bias
estimated GNSS no longer holds the block's height, so a block that settled a storey off the
model must be caught by the model alone, and one at the right height must not be."""

import numpy as np

from colmap_citymodel.align.coarse import SurfaceDistance
from colmap_citymodel.citymodel.build import store_from_polygons
from colmap_citymodel.precision.ambiguity import paired_z
from colmap_citymodel.precision.quality import QualityThresholds, height_metrics, \
    quality_verdict
from test_verdict import box

#: A storey's height (m).
STOREY = 3.0
#: GNSS's shift covariance with its bias estimated: the height free (as shift_covariances
#: gives it where the offset takes the common shift).
BIAS_FREE = np.diag([np.inf, np.inf, np.inf])


def block_of_houses():
    """Three houses of three, four and five storeys: an orbit's view, walls and some roofs."""
    return (box(0, 0, 12, 10, 3 * STOREY) + box(18, 0, 10, 12, 4 * STOREY)
            + box(0, 16, 14, 10, 5 * STOREY))


def tie_points(polygons, rng, per_wall=150, per_roof=25):
    """Tie points on the walls (many) and roofs (few) with 5 cm scatter."""
    points = []
    for ring in polygons:
        level = np.ptp(ring[:, 2]) == 0
        points.append(rng.uniform(ring.min(0), ring.max(0), (per_roof if level else per_wall, 3)))
    points = np.vstack(points)
    return points + rng.normal(0.0, 0.05, points.shape)


def test_a_block_a_storey_too_high_with_the_bias_free_fails():
    rng = np.random.default_rng(11)
    houses = block_of_houses()
    surface = SurfaceDistance(store_from_polygons(houses, origin=np.zeros(3)),
                              excluded_classes=(), threads=1)
    points = tie_points(houses, rng)
    t = QualityThresholds()

    right = height_metrics(points, surface, np.zeros(3), BIAS_FREE, t)
    assert right["p"] >= t.alpha
    assert quality_verdict({"height_placement": right, "position_sigma_m": 0.1}).verdict == "ok"

    wrong = height_metrics(points + [0.0, 0.0, STOREY], surface, np.zeros(3), BIAS_FREE, t)
    assert wrong["p"] < t.alpha
    assert abs(wrong["other_shift_m"] + STOREY) <= 0.25  # the right height, a storey down
    assert wrong["other_share"] > wrong["here_share"]
    verdict = quality_verdict({"height_placement": wrong, "position_sigma_m": 0.1})
    assert verdict.verdict == "failed"
    assert "another height" in verdict.reasons[0] and "3.0 m down" in verdict.reasons[0]


def test_gnss_that_holds_the_height_rules_a_storey_off_out():
    """GNSS that puts the block where it is, to 0.5 m with its bias, admits no height a storey
    away: the test has no alternative and the verdict stands."""
    rng = np.random.default_rng(12)
    houses = block_of_houses()
    surface = SurfaceDistance(store_from_polygons(houses, origin=np.zeros(3)),
                              excluded_classes=(), threads=1)
    points = tie_points(houses, rng) + [0.0, 0.0, STOREY]
    held = height_metrics(points, surface, np.zeros(3), np.diag([0.25, 0.25, 0.25]),
                          QualityThresholds())
    assert held["other_shift_m"] is None and held["p"] == 1.0
    assert held["reach_m"] < STOREY


def test_points_of_one_cell_count_as_one_sample():
    """The paired statistic counts cells, not points: the same gains repeated on a hundred
    points of each cell give the z of the cells alone."""
    rng = np.random.default_rng(13)
    cells = rng.normal(0.1, 0.2, 20)
    centres = np.column_stack([np.arange(20) * 25.0, np.zeros(20), np.zeros(20)])
    once = paired_z(cells, centres, 10.0)
    repeated = paired_z(np.repeat(cells, 100), np.repeat(centres, 100, axis=0)
                        + rng.uniform(0, 5, (2000, 3)), 10.0)
    assert abs(repeated - once) < 1e-9 * abs(once) + 1e-12
    # Point by point the same gains would look ten times more significant.
    naive = np.mean(np.repeat(cells, 100)) / (np.std(np.repeat(cells, 100), ddof=1) / np.sqrt(2000))
    assert naive > 5 * abs(once)
