"""Coarse alignment: the translation search finds the block where GNSS is off by more than its
stated sigma, and prefers the shift that puts most tie points on the model."""

import numpy as np
import pytest

from colmap_citymodel.align.coarse import SurfaceDistance, search_translation
from colmap_citymodel.errormodel.model import placement_score
from colmap_citymodel.options import AdjustmentOptions


def score_of(points, surface):
    """The placement score of tie points `points` without GNSS (the search's box stands for
    GNSS's sigma)."""
    return placement_score(surface, points, None, None, AdjustmentOptions())


@pytest.mark.parametrize("offset", [[18.0, 0.0, 0.0], [0.0, 18.0, 0.0], [-20.0, 4.0, 0.0],
                                    [2.0, -1.0, 1.0]])
def test_translation_search_reaches_gnss_six_sigma_off(street_scene, offset):
    """The true tie points moved off the model by 18-20 m, GNSS sigma 3 m: 6-7 sigma, beyond
    a search of +- 4 sigma (which ended 1-12 m from where it started, with 29-33 % of the
    points near the model); the default search finds the shift to the grid's 0.2 m."""
    points = np.array([p.xyz for p in street_scene.truth.points3D.values()])
    offset = np.asarray(offset)
    result = search_translation(score_of(points - offset, SurfaceDistance(street_scene.store)),
                                np.array([3.0, 3.0, 5.0]))
    np.testing.assert_allclose(result.shift, offset, atol=0.25)
    assert result.share_after > 0.9 > 0.5 > result.share_before


def test_translation_search_leaves_axes_where_gnss_is_better_than_its_grid(street_scene):
    """GNSS of RTK quality (sigma 5 / 5 / 10 cm, below the search's 0.4 m finest kernel): the
    block is not moved, although moving it back by its 0.85 m offset would put more tie points
    on the model (the search's grid cannot place a block to centimetres; GNSS does). With
    street GNSS (3 / 3 / 5 m) the same block is moved by the search."""
    from colmap_citymodel.align.coarse import PLACEMENT_RESOLUTION

    points = np.array([p.xyz for p in street_scene.truth.points3D.values()])
    offset = np.array([0.0, 0.6, 0.6])
    surface = SurfaceDistance(street_scene.store)
    precise = np.array([0.05, 0.05, 0.1])
    assert np.all(precise < PLACEMENT_RESOLUTION)
    held = search_translation(score_of(points - offset, surface), precise)
    assert np.all(held.shift == 0.0) and held.share_after == held.share_before
    moved = search_translation(score_of(points - offset, surface), np.array([3.0, 3.0, 5.0]))
    assert np.linalg.norm(moved.shift - offset) < 0.25 < np.linalg.norm(offset)
    # an axis with street GNSS is searched beside a held one
    mixed = search_translation(score_of(points - offset, surface), np.array([0.05, 3.0, 0.1]))
    assert mixed.shift[0] == 0.0 and mixed.shift[2] == 0.0 and abs(mixed.shift[1] - 0.6) < 0.25


def test_heading_search_turns_a_block_whose_gnss_heading_is_degrees_off(street_scene):
    """The true block turned by 2.5 deg about the vertical through its cameras (GNSS's heading
    over a short block: its heading sigma here is about 1 deg) and shifted by 2 m: the
    translation search alone cannot undo a turn, which puts the block's far ends a metre off
    across the street; with GNSS's heading sigma the walls' azimuths turn it back and the
    block lands within the search's grid of the truth. A heading GNSS fixes to a fraction of
    the grid (RTK) is left alone."""
    from colmap_citymodel.align.coarse import coarse_alignment, heading_sigma_deg, rotation_about
    from colmap_citymodel.block.reconstruction import camera_up_and_view, camera_centres

    rec = street_scene.truth
    points = np.array([p.xyz for p in rec.points3D.values()])
    centres = camera_centres(rec).reshape(-1, 3)
    up, view = camera_up_and_view(rec)
    centre = centres.mean(0)
    turn = rotation_about(np.array([0.0, 0.0, 1.0]), np.radians(2.5))
    shift = np.array([1.5, -1.0, 0.5])

    def moved(x):
        return (x - centre) @ turn.T + centre + shift

    surface = SurfaceDistance(street_scene.store)
    sigmas = np.array([3.0, 3.0, 5.0])
    heading_sigma = heading_sigma_deg(moved(centres), sigmas)
    assert 0.2 < heading_sigma < 2.5
    args = (moved(points), moved(centres), up @ turn.T, view @ turn.T, street_scene.store,
            score_of(moved(points), surface), sigmas, False)

    def error(alignment):
        sim3 = alignment.sim3
        back = moved(points) @ np.asarray(sim3.rotation.matrix()).T + np.asarray(sim3.translation)
        return float(np.sqrt(np.mean(np.sum((back - points) ** 2, axis=1))))

    turned = coarse_alignment(*args, heading_sigma=heading_sigma)
    assert turned.heading_deg == pytest.approx(-2.5, abs=0.3)
    assert error(turned) < 0.3
    kept = coarse_alignment(*args)
    assert kept.heading_deg is None and error(kept) > 2 * error(turned)
    rtk = coarse_alignment(*args, heading_sigma=0.05)
    assert rtk.heading_deg is None
