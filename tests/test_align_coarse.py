"""Coarse alignment: the translation search finds the block where GNSS is off by more than its
stated sigma, and prefers the shift that puts most tie points on the model."""

import numpy as np
import pytest

from colmap_citymodel.align.coarse import SurfaceDistance, search_translation


@pytest.mark.parametrize("offset", [[18.0, 0.0, 0.0], [0.0, 18.0, 0.0], [-20.0, 4.0, 0.0],
                                    [2.0, -1.0, 1.0]])
def test_translation_search_reaches_gnss_six_sigma_off(street_scene, offset):
    """The true tie points moved off the model by 18-20 m, GNSS sigma 3 m: 6-7 sigma, beyond
    a search of +- 4 sigma (which ended 1-12 m from where it started, with 29-33 % of the
    points near the model); the default search finds the shift to the grid's 0.2 m."""
    points = np.array([p.xyz for p in street_scene.truth.points3D.values()])
    offset = np.asarray(offset)
    result = search_translation(points - offset, SurfaceDistance(street_scene.store),
                                np.array([3.0, 3.0, 5.0]))
    np.testing.assert_allclose(result.shift, offset, atol=0.25)
    assert result.share_after > 0.9 > 0.5 > result.share_before
