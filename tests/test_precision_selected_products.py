"""Products with the selected inverse (precision.selected): the low-rank term rescaled on the
same factorisation, forward sweeps that start at a right-hand side's first non-zero level,
and window products assembled from per-level blocks, each against dense linear algebra."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import colmap_citymodel.precision.selected as selected
from colmap_citymodel.precision.selected import SelectedInverse, WindowProducts, window_columns

from test_precision_selected import _chain_matrix, assert_same_camera_blocks


@pytest.fixture()
def many_levels(monkeypatch):
    monkeypatch.setattr(selected, "MERGE_COLUMNS", 20)
    monkeypatch.setattr(selected, "MIN_BORDER_DEGREE", 3)
    monkeypatch.setattr(selected, "BORDER_SHARE", 0.2)


def _far_rows(n: int, rng) -> np.ndarray:
    """Rows tying blocks at the two ends of the chain (baselines far apart)."""
    h = np.zeros((4, n))
    h[:, :3] = rng.normal(size=(4, 3))
    h[:, n - 11:n - 8] = rng.normal(size=(4, 3))
    return h


def test_rescaled_low_rank_rows_share_the_factorisation(many_levels):
    s, starts, sizes = _chain_matrix()
    n = s.shape[0]
    rng = np.random.default_rng(3)
    h = _far_rows(n, rng)
    scale = np.array([10.0, 3.0, 0.5, 1.0])
    q = SelectedInverse(s, starts, sizes, low_rank=sp.csr_matrix(h))
    scaled = q.with_low_rank_scaled(scale)
    assert scaled.chol is q.chol and q.num_levels > 3
    dense = np.linalg.inv(s.toarray() + h.T @ np.diag(scale ** 2) @ h)
    tol = 1e-9 * np.abs(dense).max()
    rhs = rng.normal(size=(n, 5))
    np.testing.assert_allclose(scaled @ rhs, dense @ rhs, atol=1e-8 * np.abs(dense @ rhs).max())
    rows, cols = s.nonzero()
    np.testing.assert_allclose(scaled.pattern_values(rows, cols), dense[rows, cols], atol=tol)
    for level in range(scaled.num_levels - 1):
        columns, window = scaled.full_window(level)
        np.testing.assert_allclose(window, dense[np.ix_(columns, columns)], atol=tol)
    assert scaled.low_rank_trace() == pytest.approx(
        np.trace(np.diag(scale) @ h @ dense @ h.T @ np.diag(scale)), rel=1e-8)
    # the original keeps its own low-rank term
    unscaled = np.linalg.inv(s.toarray() + h.T @ h)
    np.testing.assert_allclose(q @ rhs, unscaled @ rhs, atol=1e-8 * np.abs(unscaled @ rhs).max())


def test_right_hand_sides_zero_above_a_level_are_solved_exactly(many_levels):
    s, starts, sizes = _chain_matrix()
    n = s.shape[0]
    rng = np.random.default_rng(4)
    q = SelectedInverse(s, starts, sizes, low_rank=sp.csr_matrix(_far_rows(n, rng)))
    dense = np.linalg.inv(s.toarray() + _far_rows(n, np.random.default_rng(4)).T
                          @ _far_rows(n, np.random.default_rng(4)))
    perm, bounds = q.levels.perm, q.levels.bounds
    rhs = np.zeros((n, 6))
    for j, level in enumerate([3, 0, q.num_levels - 1, 1, 2]):  # first non-zero level
        rows = perm[bounds[level]:bounds[-1]]
        rhs[rows, j] = rng.normal(size=len(rows))
    # column 5 all zero; the border columns of column 0 too
    rhs[q.levels.border, 0] = 1.0
    expected = dense @ rhs
    np.testing.assert_allclose(q @ rhs, expected, atol=1e-8 * np.abs(expected).max())
    assert np.all((q @ rhs)[:, 5] == 0.0)
    np.testing.assert_allclose(q @ rhs[:, 2], expected[:, 2],
                               atol=1e-8 * np.abs(expected).max())


def test_window_products_equal_the_dense_product(many_levels):
    """Symmetric products (V M V^T, d d^T) per window, the windows asked for in order and
    again out of it."""
    s, starts, sizes = _chain_matrix()
    q = SelectedInverse(s, starts, sizes)
    rng = np.random.default_rng(5)
    right = rng.normal(size=(q.nc, 7))
    m = rng.normal(size=(7, 7))
    left = right @ (m @ m.T)  # V M with M symmetric: the product is symmetric
    for products, other in ((WindowProducts(q.levels, left, right), right),
                            (WindowProducts(q.levels, left), left)):
        for level in list(range(q.num_levels)) + [2, 1]:  # ascending, then asked again
            columns = window_columns(q.levels, level)
            np.testing.assert_allclose(products.window(level),
                                       left[columns] @ other[columns].T, rtol=1e-12,
                                       atol=1e-12)


def test_solve_weights_with_every_hold_in_the_low_rank_term(many_levels):
    """Holds of the scale alone (baselines between far images, all in the low-rank term): the
    solve-weighted cofactors share the relaxed ones' factorisation and equal a new system at
    the solve's weights."""
    from colmap_citymodel.adjust.problem import BaselinePriors
    from colmap_citymodel.precision.estimate import cofactors, solve_weighted

    from test_precision_estimate import _tiny

    def holds(rec):
        ids = np.array(sorted(rec.reg_image_ids()))
        centres = np.array([rec.image(int(i)).projection_center() for i in ids])
        pairs = np.array([[ids[0], ids[-1]], [ids[1], ids[-2]]])
        lengths = np.linalg.norm(centres[[0, 1]] - centres[[-1, -2]], axis=1)
        return BaselinePriors(pairs, lengths, np.full(2, 0.01), tightening=10.0)

    problem = _tiny(holds=holds)
    assert len(problem.hold_relaxation) == 2
    relaxed = cofactors(problem, keep_system=True, method="selected", redundancy=False)
    assert len(relaxed.far_rows) == 2
    fresh = cofactors(problem, keep_system=True, method="selected", redundancy=False,
                      relax_holds=False, points=False)
    ours = solve_weighted(problem, relaxed)
    assert ours.q_cc.chol is relaxed.q_cc.chol  # no new factorisation
    layout = fresh.layout
    assert_same_camera_blocks(ours, fresh)
    rhs = np.random.default_rng(6).normal(size=(layout.num_c, 3))
    np.testing.assert_allclose(ours.q_cc @ rhs, fresh.q_cc @ rhs,
                               atol=1e-8 * np.abs(fresh.q_cc @ rhs).max())
    relaxed_q = relaxed.q_cc @ rhs  # the relaxed system keeps its own weights
    assert np.abs(relaxed_q - fresh.q_cc @ rhs).max() > 1e-6 * np.abs(relaxed_q).max()
