"""Selected inversion (precision.selected, precision.point_cofactors) against the dense inverse,
and the datum's common shift in the stated image and point covariances."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import colmap_citymodel.precision.selected as selected
from colmap_citymodel.precision.estimate import (
    cofactors,
    datum_shift,
    estimate_precision,
    generalisation_effects,
)
from colmap_citymodel.precision.selected import SelectedInverse

from test_precision_estimate import _tiny


@pytest.fixture()
def many_levels(monkeypatch):
    """Small levels and a border even on a tiny problem, so every code path is taken."""
    monkeypatch.setattr(selected, "MERGE_COLUMNS", 20)
    monkeypatch.setattr(selected, "MIN_BORDER_DEGREE", 3)
    monkeypatch.setattr(selected, "BORDER_SHARE", 0.2)


def _chain_matrix(num_blocks: int = 40, size: int = 3, reach: int = 2, seed: int = 0):
    """SPD normal matrix of blocks coupled to their `reach` neighbours and one global block."""
    rng = np.random.default_rng(seed)
    n = num_blocks * size + 2
    rows = []
    for k in range(num_blocks):
        for j in range(k, min(num_blocks, k + reach + 1)):
            row = np.zeros(n)
            row[k * size:(k + 1) * size] = rng.normal(size=size)
            row[j * size:(j + 1) * size] += rng.normal(size=size)
            row[-2:] = rng.normal(size=2)  # the global unknowns couple to everything
            rows.append(row)
    a = np.array(rows * 3) + 0.1 * rng.normal(size=(3 * len(rows), n)) * (np.array(rows * 3) != 0)
    s = a.T @ a + np.eye(n) * 1e-3
    sizes = np.array([size] * num_blocks + [2])
    return sp.csr_matrix(s), np.concatenate([[0], np.cumsum(sizes)[:-1]]), sizes


def test_selected_inverse_equals_the_dense_inverse_on_its_pattern(many_levels):
    s, starts, sizes = _chain_matrix()
    q = SelectedInverse(s, starts, sizes)
    assert q.num_levels > 3 and len(q.levels.border) == 2
    dense = np.linalg.inv(s.toarray())
    rows, cols = s.nonzero()
    np.testing.assert_allclose(q.pattern_values(rows, cols), dense[rows, cols],
                               atol=1e-9 * np.abs(dense).max())
    for k in range(len(sizes)):
        block = np.arange(starts[k], starts[k] + sizes[k])
        np.testing.assert_allclose(q[block, block], dense[np.ix_(block, block)],
                                   atol=1e-9 * np.abs(dense).max())
    rhs = np.random.default_rng(1).normal(size=(s.shape[0], 4))
    np.testing.assert_allclose(q @ rhs, dense @ rhs, atol=1e-8 * np.abs(dense @ rhs).max())
    with pytest.raises(ValueError):  # pairs that are not coupled are not held
        q.pattern_values(np.array([0]), np.array([s.shape[0] - 3]))


def test_low_rank_rows_coupling_far_blocks(many_levels):
    """Rows tying the first block to the last (baseline holds) enter by Woodbury: the levels
    stay those of the rest, the inverse is that of the whole."""
    s, starts, sizes = _chain_matrix()
    n = s.shape[0]
    rng = np.random.default_rng(2)
    h = np.zeros((3, n))
    h[:, :3] = rng.normal(size=(3, 3))
    h[:, n - 8:n - 5] = rng.normal(size=(3, 3))
    q = SelectedInverse(s, starts, sizes, low_rank=sp.csr_matrix(h))
    assert q.num_levels > 3
    dense = np.linalg.inv(s.toarray() + h.T @ h)
    rows, cols = s.nonzero()
    np.testing.assert_allclose(q.pattern_values(rows, cols), dense[rows, cols],
                               atol=1e-9 * np.abs(dense).max())
    block = np.arange(n - 8, n - 5)
    np.testing.assert_allclose(q[block, block], dense[np.ix_(block, block)],
                               atol=1e-9 * np.abs(dense).max())
    rhs = rng.normal(size=n)
    np.testing.assert_allclose(q @ rhs, dense @ rhs, atol=1e-8 * np.abs(dense @ rhs).max())
    assert q.low_rank_trace() == pytest.approx(np.trace(h @ dense @ h.T), rel=1e-8)


def test_singular_matrix_raises():
    s, starts, sizes = _chain_matrix(num_blocks=6)
    s = s.tolil()
    s[0, :] = 0.0
    s[:, 0] = 0.0
    with pytest.raises(np.linalg.LinAlgError):
        SelectedInverse(s.tocsr(), starts, sizes)


@pytest.fixture(scope="module")
def tiny():
    # Every tie point alike: the generalisation's "consider" path beside the classical one.
    return _tiny(face_weighting="per_point")


def test_selected_cofactors_match_the_dense_computation(tiny, many_levels):
    dense = cofactors(tiny, keep_system=True, method="dense")
    ours = cofactors(tiny, keep_system=True, method="selected")
    assert ours.q_cc.num_levels > 3 and len(ours.q_cc.levels.border)
    np.testing.assert_allclose(ours.q_points, dense.q_points, rtol=1e-8,
                               atol=1e-10 * np.abs(dense.q_points).max())
    for g, r in dense.redundancy_by_group.items():
        assert ours.redundancy_by_group[g] == pytest.approx(r, abs=1e-6)
    layout = dense.layout
    for (kind, key) in layout.names[:len(layout.names) - len(layout.point_ids)]:
        columns = layout.columns(kind, key)
        np.testing.assert_allclose(ours.q_cc[columns, columns], dense.q_cc[columns, columns],
                                   atol=1e-10 * np.abs(dense.q_cc).max())
    a = generalisation_effects(tiny, dense, 0.2)
    b = generalisation_effects(tiny, ours, 0.2)
    np.testing.assert_allclose(b.camera, a.camera, atol=1e-9 * np.abs(a.camera).max())
    np.testing.assert_allclose(b.points_cov, a.points_cov,
                               atol=1e-9 * np.abs(a.points_cov).max())
    assert b.sigma_estimated == pytest.approx(a.sigma_estimated, rel=1e-8)


def test_per_image_sigmas_of_the_selected_path_match_the_dense_one(tiny, monkeypatch):
    import colmap_citymodel.precision.estimate as estimate

    dense = estimate_precision(tiny, sigma_generalisation=0.2)
    monkeypatch.setattr(estimate, "DENSE_MAX_UNKNOWNS", 0)
    monkeypatch.setattr(selected, "MERGE_COLUMNS", 20)
    ours = estimate_precision(tiny, sigma_generalisation=0.2)
    assert len(ours.image_cov) == 12 and ours.generalisation == "consider"
    np.testing.assert_allclose(ours.image_sigmas, dense.image_sigmas, rtol=1e-7)
    np.testing.assert_allclose(ours.point_sigmas, dense.point_sigmas, rtol=1e-7)
    np.testing.assert_allclose(ours.aware_sigmas("image_cov"), dense.aware_sigmas("image_cov"),
                               rtol=1e-7)
    assert ours.variance.sigma0 == pytest.approx(dense.variance.sigma0, rel=1e-9)


def test_no_image_centre_is_stated_more_precise_than_the_datum(tiny):
    plain = estimate_precision(tiny)
    before = plain.aware_sigmas("image_cov")
    before = _sigmas_rad(plain) if before is None else before
    least = before[:, :3].min(axis=0)
    datum = np.array([least[0] * 4.0, np.nan, least[2] * 0.5])  # E above, N unstated, U below
    ours = estimate_precision(tiny, datum_sigmas=datum)
    shift = np.sqrt(ours.datum_shift_variance)
    assert shift[0] > 0 and shift[1] == 0 and shift[2] == 0
    aware = ours.aware_sigmas("image_cov")
    assert aware[:, 0].min() == pytest.approx(datum[0], rel=1e-9)
    np.testing.assert_allclose(aware[:, 1:], before[:, 1:], rtol=1e-9)
    points = ours.aware_sigmas("point_cov")  # the tie points move with the block
    base = plain.aware_sigmas("point_cov")
    base = plain.point_sigmas if base is None else base
    np.testing.assert_allclose(points[:, 0] ** 2, base[:, 0] ** 2 + shift[0] ** 2, rtol=1e-9)
    summary = ours.summary()
    assert summary["datum_shift"]["sigma_m"]["E"] == pytest.approx(shift[0])
    assert summary["datum_shift"]["median_image_sigma_m"]["X0"] >= datum[0]


def _sigmas_rad(precision) -> np.ndarray:
    return np.sqrt(np.diagonal(precision.image_cov, axis1=1, axis2=2))


def test_datum_shift_is_what_the_least_precise_axis_lacks():
    cov = np.stack([np.diag([0.01, 0.04, 0.09]), np.diag([0.02, 0.01, 0.16])])
    np.testing.assert_allclose(datum_shift(cov, np.array([0.2, 0.05, np.nan])),
                               [0.04 - 0.01, 0.0, 0.0])
    assert not datum_shift(cov, None).any()


def test_solve_weighted_cofactors_equal_a_new_system_at_the_solve_weights(many_levels):
    """The holds re-weighted in S alone give the same Q_cc as the Jacobian at the solve's
    weights, densely and selected."""
    from colmap_citymodel.adjust.problem import BaselinePriors
    from colmap_citymodel.precision.estimate import solve_weighted

    def holds(rec):
        ids = np.array(sorted(rec.reg_image_ids()))
        centres = np.array([rec.image(int(i)).projection_center() for i in ids])
        pairs = np.array([[ids[0], ids[-1]], [ids[1], ids[-2]]])
        lengths = np.linalg.norm(centres[[0, 1]] - centres[[-1, -2]], axis=1)
        return BaselinePriors(pairs, lengths, np.full(2, 0.01), level_image=int(ids[3]),
                              level_position=centres[3], level_sigmas=np.full(3, 0.01),
                              tightening=10.0, level_tightening=5.0)

    problem = _tiny(holds=holds)
    assert len(problem.hold_relaxation) == 5
    dense = cofactors(problem, method="dense")
    ours = cofactors(problem, method="selected")
    assert len(ours.far_rows) == 2  # the two baselines, as a low-rank term
    for g, r in dense.redundancy_by_group.items():
        assert ours.redundancy_by_group[g] == pytest.approx(r, abs=1e-6)
    np.testing.assert_allclose(ours.q_points, dense.q_points, rtol=1e-8,
                               atol=1e-10 * np.abs(dense.q_points).max())
    for method in ("dense", "selected"):
        relaxed = cofactors(problem, keep_system=True, method=method, redundancy=False)
        fresh = cofactors(problem, keep_system=True, method=method, redundancy=False,
                          relax_holds=False, points=False)
        ours = solve_weighted(problem, relaxed)
        layout = fresh.layout
        assert_same_camera_blocks(ours, fresh)
        rhs = np.ones(layout.num_c)
        np.testing.assert_allclose(ours.q_cc @ rhs, fresh.q_cc @ rhs, rtol=1e-7)


def assert_same_camera_blocks(ours, fresh) -> None:
    """Each camera-side unknown's block of `ours.q_cc` equals `fresh`'s (points left out)."""
    layout = fresh.layout
    for (kind, key) in layout.names[:len(layout.names) - len(layout.point_ids)]:
        columns = layout.columns(kind, key)
        expected = np.asarray(fresh.q_cc[columns, columns])
        np.testing.assert_allclose(ours.q_cc[columns, columns], expected,
                                   atol=1e-9 * np.abs(expected).max())


def test_selected_image_sigmas_cover_the_true_centre_errors(monkeypatch):
    """Correctly weighted tiny blocks (image noise and GNSS drawn with their stated sigmas, the
    true model): the true centre errors against the stated covariance (selected path) are
    chi-square with 3 degrees of freedom, so mean e^T C^-1 e ~ 3 and ~95 % inside the 95 %
    ellipsoid (the 12 images of a block share much of their error: bounds for ~10 blocks).
    Every tie point alike, the stochastic model of exact planes (faces' offsets free by a
    0.2 m prior would state sigmas the exact model does not need)."""
    import colmap_citymodel.precision.estimate as estimate
    from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene

    monkeypatch.setattr(estimate, "DENSE_MAX_UNKNOWNS", 0)
    distances = []
    for seed in range(3, 11):
        problem = _tiny(seed=seed, face_weighting="per_point")
        scene = make_street_scene(StreetSceneOptions(num_stations=4, point_spacing=2.5,
                                                     image_noise_px=1.0, seed=seed))
        truth = {im.name: np.asarray(im.projection_center())
                 for im in scene.truth.images.values()}
        result = estimate_precision(problem)
        for name, centre, cov in zip(result.image_names, result.centres, result.image_cov):
            error = centre - truth[name]
            distances.append(error @ np.linalg.solve(cov[:3, :3], error))
    distances = np.array(distances)
    assert 2.0 < distances.mean() < 4.5
    assert np.mean(distances < 7.81) > 0.85  # chi2(3) 95 % quantile


def test_vectorised_image_jacobians_equal_the_per_image_ones(tiny):
    from colmap_citymodel.precision.estimate import (
        _image_quantities,
        image_jacobian,
        image_jacobians,
    )

    rec = tiny.reconstruction
    ids = list(rec.reg_image_ids())
    values, jacobians = image_jacobians(rec, ids)
    for k, image_id in enumerate(ids):
        image = rec.image(image_id)
        expected = _image_quantities(rec, image, rec.frame(image.frame_id).rig_from_world)
        np.testing.assert_allclose(values[k], expected, atol=1e-12)
        np.testing.assert_allclose(jacobians[k], image_jacobian(rec, image_id), atol=1e-6)
