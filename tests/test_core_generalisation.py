"""Cost functions of the generalisation-aware stochastic model: the tie point to plane
distance with a per-plane offset unknown, and the scalar prior on that offset. Closed form,
Jacobians against finite differences, and the offset acting on a shared block in a problem."""

from __future__ import annotations

import numpy as np
import pyceres
import pytest
from test_core_costs import evaluate, numeric_jacobians

from colmap_citymodel import _ext


@pytest.fixture(scope="module")
def core():
    return _ext.load_core()


def test_point_plane_offset_distance_closed_form_and_jacobians(core):
    rng = np.random.default_rng(1)
    for _ in range(5):
        point = rng.normal(scale=20.0, size=3)
        normal = rng.normal(size=3)  # not unit: the cost divides by |n|
        offset = rng.normal(size=1)
        generalisation = rng.normal(scale=0.3, size=1)
        sigma = rng.uniform(0.01, 0.5)
        cost = core.PointPlaneOffsetDistanceCost(sigma)
        assert cost.num_residuals() == 1
        assert cost.parameter_block_sizes() == [3, 3, 1, 1]
        residuals, jacobians = evaluate(cost, point, normal, offset, generalisation)
        unit = normal / np.linalg.norm(normal)
        expected = (unit @ point + offset[0] + generalisation[0]) / sigma
        np.testing.assert_allclose(residuals, [expected], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(jacobians[0].ravel(), unit / sigma, rtol=1e-12)
        np.testing.assert_allclose(jacobians[2].ravel(), [1.0 / sigma], rtol=1e-12)
        np.testing.assert_allclose(jacobians[3].ravel(), [1.0 / sigma], rtol=1e-12)
        for analytic, numeric in zip(
                jacobians, numeric_jacobians(cost, [point, normal, offset, generalisation]),
                strict=True):
            np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-6)
        # Without offset it is the plain point-plane distance.
        plain, _ = evaluate(core.PointPlaneDistanceCost(sigma), point, normal, offset)
        zero, _ = evaluate(cost, point, normal, offset, np.zeros(1))
        np.testing.assert_allclose(zero, plain, rtol=1e-12)


def test_scalar_prior_closed_form_and_jacobian(core):
    cost = core.ScalarPriorCost(0.25, 0.2)
    assert cost.parameter_block_sizes() == [1]
    residuals, jacobians = evaluate(cost, np.array([-0.15]))
    np.testing.assert_allclose(residuals, [(-0.15 - 0.25) / 0.2], rtol=1e-12)
    np.testing.assert_allclose(jacobians[0], [[5.0]], rtol=1e-12)
    np.testing.assert_allclose(jacobians[0], numeric_jacobians(cost, [np.array([0.7])])[0],
                               rtol=1e-8)


@pytest.mark.parametrize("bad", [0.0, -0.1, float("nan"), float("inf")])
def test_generalisation_costs_reject_bad_sigma(core, bad):
    with pytest.raises(ValueError):
        core.PointPlaneOffsetDistanceCost(bad)
    with pytest.raises(ValueError):
        core.ScalarPriorCost(0.0, bad)
    with pytest.raises(ValueError):
        core.ScalarPriorCost(float("nan"), 0.1)


def test_shared_offset_is_the_prior_weighted_mean_of_the_points_distances(core):
    # Points at distances z_i from the fixed plane z = 0, one shared offset o with a prior
    # N(0, s_o^2), sigma s per point: o = -sum(z)/s^2 / (n/s^2 + 1/s_o^2) (linear least squares).
    rng = np.random.default_rng(2)
    z = 0.3 + rng.normal(scale=0.05, size=40)
    sigma, sigma_o = 0.05, 0.2
    normal = np.array([0.0, 0.0, 1.0])
    offset = np.zeros(1)
    generalisation = np.zeros(1)
    points = [np.array([rng.normal(), rng.normal(), zi]) for zi in z]
    problem = pyceres.Problem()
    cost = core.PointPlaneOffsetDistanceCost(sigma)
    prior = core.ScalarPriorCost(0.0, sigma_o)
    for point in points:
        problem.add_residual_block(cost, None, [point, normal, offset, generalisation])
        problem.set_parameter_block_constant(point)
    problem.set_parameter_block_constant(normal)
    problem.set_parameter_block_constant(offset)
    problem.add_residual_block(prior, None, [generalisation])
    options = pyceres.SolverOptions()
    options.function_tolerance = options.gradient_tolerance = 1e-16
    options.parameter_tolerance = 1e-16
    summary = pyceres.SolverSummary()
    pyceres.solve(options, problem, summary)
    expected = -np.sum(z) / sigma ** 2 / (len(z) / sigma ** 2 + 1.0 / sigma_o ** 2)
    assert generalisation[0] == pytest.approx(expected, rel=1e-6)
