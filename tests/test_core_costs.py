"""Cost functions of colmap_citymodel._core: closed form, Jacobians, and use inside COLMAP's BA.

The end-to-end test adds point-to-plane residuals to the problem of
`pycolmap.create_default_ceres_bundle_adjuster`, i.e. it fails if the extension does not share
pybind11 internals with pycolmap/pyceres or if our residuals do not act on COLMAP's own blocks.
"""

from __future__ import annotations

import importlib
import types

import numpy as np
import pyceres
import pycolmap
import pycolmap.cost_functions
import pytest

from colmap_citymodel import _ext
from colmap_citymodel.block.reconstruction import position_in_rig
from colmap_citymodel.errors import ExtensionImportError

#: COLMAP 4's pose parameter block: Rigid3d.params, quaternion xyzw + translation.
POSE_BLOCK_SIZE = 7


@pytest.fixture(scope="module")
def core():
    return _ext.load_core()


def evaluate(cost, *blocks):
    """Residuals (r,) and Jacobians [(r, size_i)] through pyceres's CostFunction.evaluate."""
    residuals, jacobians = cost.evaluate(*[np.ascontiguousarray(b, dtype=float) for b in blocks])
    assert residuals is not None, "Evaluate returned false"
    return residuals.ravel(), [np.asarray(j) for j in jacobians]


def numeric_jacobians(cost, blocks, step=1e-6):
    """Central finite differences of the cost's own residuals, per block and coordinate."""
    blocks = [np.array(b, dtype=float) for b in blocks]
    jacobians = []
    for i, block in enumerate(blocks):
        cols = []
        for k in range(block.size):
            plus = [b.copy() for b in blocks]
            minus = [b.copy() for b in blocks]
            plus[i][k] += step
            minus[i][k] -= step
            cols.append((evaluate(cost, *plus)[0] - evaluate(cost, *minus)[0]) / (2 * step))
        jacobians.append(np.stack(cols, axis=1))
    return jacobians


def random_pose(rng) -> pycolmap.Rigid3d:
    rotation = pycolmap.Rotation3d(rng.normal(size=3))  # axis-angle
    return pycolmap.Rigid3d(rotation, rng.normal(scale=10.0, size=3))


# ---------------------------------------------------------------- point-plane distance


def test_point_plane_distance_closed_form_and_jacobians(core):
    rng = np.random.default_rng(0)
    for _ in range(5):
        point = rng.normal(scale=20.0, size=3)
        normal = rng.normal(size=3)  # deliberately not unit: the cost divides by |n|
        offset = rng.normal(size=1)
        sigma = rng.uniform(0.01, 0.5)
        cost = core.PointPlaneDistanceCost(sigma)
        assert cost.num_residuals() == 1
        assert cost.parameter_block_sizes() == [3, 3, 1]

        residuals, jacobians = evaluate(cost, point, normal, offset)
        unit = normal / np.linalg.norm(normal)
        expected = (unit @ point + offset[0]) / sigma
        np.testing.assert_allclose(residuals, [expected], rtol=1e-12, atol=1e-12)
        # Closed-form Jacobians: d/dX = n/|n|/sigma, d/dd = 1/sigma.
        np.testing.assert_allclose(jacobians[0].ravel(), unit / sigma, rtol=1e-12)
        np.testing.assert_allclose(jacobians[2].ravel(), [1.0 / sigma], rtol=1e-12)
        for analytic, numeric in zip(
            jacobians, numeric_jacobians(cost, [point, normal, offset]), strict=True
        ):
            np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-6)


def test_point_plane_distance_is_zero_on_the_plane(core):
    normal = np.array([0.0, 0.6, 0.8])
    offset = np.array([-3.0])
    on_plane = np.array([5.0, 1.0, 3.0])
    on_plane -= (normal @ on_plane + offset[0]) * normal
    residuals, _ = evaluate(core.PointPlaneDistanceCost(0.2), on_plane, normal, offset)
    assert abs(residuals[0]) < 1e-12
    above = on_plane + 0.3 * normal
    residuals, _ = evaluate(core.PointPlaneDistanceCost(0.2), above, normal, offset)
    assert residuals[0] == pytest.approx(0.3 / 0.2, rel=1e-12)


def test_point_plane_distance_at_a_reference_point(core):
    """The offset may refer to a point P0 on the plane: (n.(X - P0)/|n| + d) / sigma; the
    same plane as n.X + d - n.P0 = 0, with its own closed form and Jacobians."""
    rng = np.random.default_rng(1)
    for _ in range(5):
        point = rng.normal(scale=20.0, size=3) + 300.0
        reference = rng.normal(scale=5.0, size=3) + 300.0
        normal = rng.normal(size=3)
        offset = rng.normal(size=1)
        sigma = rng.uniform(0.01, 0.5)
        for factory, extra in ((core.PointPlaneDistanceCost, []),
                               (core.PointPlaneOffsetDistanceCost, [np.array([0.3])])):
            cost = factory(sigma, reference)
            residuals, jacobians = evaluate(cost, point, normal, offset, *extra)
            unit = normal / np.linalg.norm(normal)
            expected = (unit @ (point - reference) + offset[0] + sum(e[0] for e in extra)) / sigma
            np.testing.assert_allclose(residuals, [expected], rtol=1e-10)
            for analytic, numeric in zip(
                jacobians, numeric_jacobians(cost, [point, normal, offset, *extra]), strict=True
            ):
                np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="reference"):
        core.PointPlaneDistanceCost(0.1, np.array([0.0, np.nan, 0.0]))


@pytest.mark.parametrize("sigma", [0.0, -1.0, float("nan"), float("inf")])
def test_point_plane_distance_rejects_bad_sigma(core, sigma):
    with pytest.raises(ValueError, match="sigma"):
        core.PointPlaneDistanceCost(sigma)


# ---------------------------------------------------------------- point position prior


def test_point_position_prior_per_axis_sigma(core):
    observed = np.array([10.0, -4.0, 2.5])
    sigma = np.array([0.01, 0.02, 0.5])
    point = observed + np.array([0.03, -0.01, 1.0])
    cost = core.PointPositionPriorCost(observed, sigma_xyz=sigma)
    residuals, jacobians = evaluate(cost, point)
    np.testing.assert_allclose(residuals, (point - observed) / sigma, rtol=1e-12)
    np.testing.assert_allclose(jacobians[0], np.diag(1.0 / sigma), rtol=1e-12)
    np.testing.assert_allclose(jacobians[0], numeric_jacobians(cost, [point])[0], atol=1e-5)


def test_point_position_prior_full_covariance(core):
    rng = np.random.default_rng(1)
    a = rng.normal(size=(3, 3))
    covariance = a @ a.T + 0.1 * np.eye(3)
    sqrt_info = _ext.sqrt_information(covariance)
    np.testing.assert_allclose(sqrt_info.T @ sqrt_info, np.linalg.inv(covariance), atol=1e-10)
    observed = rng.normal(size=3)
    point = rng.normal(size=3)
    cost = core.PointPositionPriorCost(observed, sqrt_information=sqrt_info)
    residuals, jacobians = evaluate(cost, point)
    np.testing.assert_allclose(residuals, sqrt_info @ (point - observed), rtol=1e-10, atol=1e-12)
    # Whitened squared norm is the Mahalanobis distance.
    diff = point - observed
    assert residuals @ residuals == pytest.approx(diff @ np.linalg.solve(covariance, diff))
    np.testing.assert_allclose(jacobians[0], sqrt_info, rtol=1e-12)


def test_point_position_prior_rejects_bad_input(core):
    with pytest.raises(ValueError, match="sigma_xyz"):
        core.PointPositionPriorCost(np.zeros(3), sigma_xyz=np.array([1.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="invertible"):
        core.PointPositionPriorCost(np.zeros(3), sqrt_information=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="positive definite"):
        _ext.sqrt_information(-np.eye(3))


# ---------------------------------------------------------------- projection-centre prior


def test_projection_center_prior_closed_form_and_jacobians(core):
    rng = np.random.default_rng(2)
    for _ in range(5):
        rig_from_world = random_pose(rng)
        position_in_rig = rng.normal(scale=0.5, size=3)
        observed = rng.normal(scale=10.0, size=3)
        sigma = np.array([3.0, 3.0, 5.0])
        cost = core.ProjectionCenterPriorCost(observed, sigma, position_in_rig)
        assert cost.parameter_block_sizes() == [POSE_BLOCK_SIZE]

        params = np.array(rig_from_world.params)
        residuals, jacobians = evaluate(cost, params)
        position = rig_from_world.inverse() * position_in_rig  # world_from_rig * p_in_rig
        np.testing.assert_allclose(residuals, (position - observed) / sigma, atol=1e-10)
        numeric = numeric_jacobians(cost, [params])[0]
        np.testing.assert_allclose(jacobians[0], numeric, rtol=1e-5, atol=1e-6)


def test_projection_center_prior_agrees_with_pycolmap_position_prior(core):
    """pycolmap's AbsolutePosePositionPriorCost fits COLMAP 4's 7-parameter frame block for a
    reference sensor; ours gives the same residual (opposite sign) and adds offsets in the rig."""
    rng = np.random.default_rng(3)
    rig_from_world = random_pose(rng)
    params = np.array(rig_from_world.params)
    observed = rng.normal(scale=10.0, size=3)
    theirs = pycolmap.cost_functions.AbsolutePosePositionPriorCost(observed)
    assert theirs.parameter_block_sizes() == [7]
    ours = core.ProjectionCenterPriorCost(observed, np.ones(3))
    r_theirs, j_theirs = evaluate(theirs, params)
    r_ours, j_ours = evaluate(ours, params)
    np.testing.assert_allclose(r_ours, -r_theirs, atol=1e-10)
    np.testing.assert_allclose(j_ours[0], -j_theirs[0], atol=1e-9)


def test_projection_center_prior_on_rig_frames_gives_camera_centres(core):
    """For every image of a 2-camera rig, the prior evaluated on the frame's pose block with
    position_in_rig() is zero exactly at the image's projection centre."""
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs = 1
    options.num_cameras_per_rig = 2
    options.num_frames_per_rig = 3
    options.num_points3D = 20
    reconstruction = pycolmap.synthesize_dataset(options)
    non_ref = 0
    for image_id, image in reconstruction.images.items():
        block = reconstruction.frames[image.frame_id].rig_from_world.params
        offset = position_in_rig(reconstruction, image)
        non_ref += bool(np.any(offset != 0))
        centre = image.projection_center()
        cost = core.ProjectionCenterPriorCost(centre, np.ones(3), offset)
        np.testing.assert_allclose(evaluate(cost, block)[0], 0.0, atol=1e-9)
        shifted = core.ProjectionCenterPriorCost(centre + [1.0, 2.0, 3.0], np.ones(3), offset)
        np.testing.assert_allclose(evaluate(shifted, block)[0], [-1.0, -2.0, -3.0], atol=1e-9)
    assert non_ref == 3  # one non-reference camera per frame


@pytest.mark.parametrize("directions", [np.array([[0.0], [0.0], [1.0]]), np.eye(3)],
                         ids=["height", "bias"])
def test_projection_center_offset_prior_closed_form_and_jacobians(core, directions):
    rng = np.random.default_rng(5)
    k = directions.shape[1]
    for _ in range(5):
        rig_from_world = random_pose(rng)
        position_in_rig = rng.normal(scale=0.5, size=3)
        observed = rng.normal(scale=10.0, size=3)
        offset = rng.normal(scale=50.0, size=k)
        sigma = np.array([3.0, 3.0, 5.0])
        cost = core.ProjectionCenterOffsetPriorCost(observed, sigma, position_in_rig,
                                                    directions)
        assert cost.parameter_block_sizes() == [POSE_BLOCK_SIZE, k]

        params = np.array(rig_from_world.params)
        residuals, jacobians = evaluate(cost, params, offset)
        position = rig_from_world.inverse() * position_in_rig
        expected = (position - observed - directions @ offset) / sigma
        np.testing.assert_allclose(residuals, expected, atol=1e-10)
        # d r / d b = -D / sigma (closed form); the pose part as the plain prior's.
        np.testing.assert_allclose(jacobians[1], -directions / sigma[:, None], atol=1e-12)
        numeric = numeric_jacobians(cost, [params, offset])
        np.testing.assert_allclose(jacobians[0], numeric[0], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(jacobians[1], numeric[1], rtol=1e-5, atol=1e-6)
        plain = core.ProjectionCenterPriorCost(observed + directions @ offset, sigma,
                                               position_in_rig)
        r_plain, j_plain = evaluate(plain, params)
        np.testing.assert_allclose(residuals, r_plain, atol=1e-10)
        np.testing.assert_allclose(jacobians[0], j_plain[0], atol=1e-10)


def test_projection_center_offset_prior_rejects_bad_directions(core):
    with pytest.raises(ValueError, match="1 or 3 columns"):
        core.ProjectionCenterOffsetPriorCost(np.zeros(3), np.ones(3), np.zeros(3),
                                             np.zeros((3, 2)))
    with pytest.raises(ValueError, match="3 x k"):
        core.ProjectionCenterOffsetPriorCost(np.zeros(3), np.ones(3), np.zeros(3),
                                             np.zeros((2, 1)))


# ---------------------------------------------------------------- extension loading errors


def test_load_core_reports_missing_extension(monkeypatch):
    real_import = importlib.import_module

    def fake_import(name, *args):
        if name == "colmap_citymodel._core":
            raise ModuleNotFoundError("No module named 'colmap_citymodel._core'", name=name)
        return real_import(name, *args)

    monkeypatch.setattr(_ext.importlib, "import_module", fake_import)
    with pytest.raises(ExtensionImportError, match="not built.*pip install --no-build-isolation"):
        _ext._import_core()


def test_load_core_reports_pybind11_internals_mismatch():
    def unconvertible(sigma):
        # What pybind11 raises when the returned ceres::CostFunction* is unknown to our internals.
        raise TypeError("Unable to convert function return value to a Python type!")

    fake = types.SimpleNamespace(
        PointPlaneDistanceCost=unconvertible,
        __pybind11_internals_version__=12,
        __pybind11_version__="3.1.0",
    )
    with pytest.raises(ExtensionImportError, match=r"internals v12.*pybind11 3\.0\.x"):
        _ext._self_check(fake)


def test_load_core_self_check_passes_on_the_built_extension(core):
    assert core.__pybind11_internals_version__ == _ext.EXPECTED_PYBIND11_INTERNALS_VERSION
    _ext._self_check(core)


# ---------------------------------------------------------------- inside COLMAP's bundle adjuster


def _planar_scene(seed: int, pixel_noise: float):
    """Synthetic reconstruction in which half of the points lie on a known plane.

    Returns (reconstruction, planar point ids, true plane (n, d), true xyz by id). Observations
    of all points are re-projected from the truth plus Gaussian pixel noise.
    """
    rng = np.random.default_rng(seed)
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs = 1
    options.num_cameras_per_rig = 1
    options.num_frames_per_rig = 8
    options.num_points3D = 120
    options.num_points2D_without_point3D = 0
    pycolmap.set_random_seed(seed)  # synthesize_dataset draws from COLMAP's global generator
    reconstruction = pycolmap.synthesize_dataset(options)

    ids = sorted(reconstruction.points3D)
    xyz = np.array([reconstruction.points3D[i].xyz for i in ids])
    normal = np.array([0.3, -0.2, 0.93])
    normal /= np.linalg.norm(normal)
    offset = -float(normal @ xyz.mean(axis=0))
    planar = ids[::2]
    truth = {}
    for point_id in ids:
        point = reconstruction.points3D[point_id]
        if point_id in planar:
            point.xyz -= (normal @ point.xyz + offset) * normal
        truth[point_id] = point.xyz.copy()
        for element in point.track.elements:
            image = reconstruction.images[element.image_id]
            xy = image.project_point(point.xyz)
            image.points2D[element.point2D_idx].xy = xy + rng.normal(scale=pixel_noise, size=2)
    return reconstruction, planar, (normal, offset), truth


def _adjuster(reconstruction):
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.images:
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.refine_focal_length = False
    options.refine_extra_params = False
    options.refine_principal_point = False
    return pycolmap.create_default_ceres_bundle_adjuster(options, config, reconstruction)


def _off_plane(reconstruction, point_ids, normal, offset):
    xyz = np.array([reconstruction.points3D[i].xyz for i in point_ids])
    return xyz @ normal + offset


def _best_fit_plane_rms(xyz: np.ndarray) -> float:
    centred = xyz - xyz.mean(axis=0)
    return float(np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(len(xyz)))


def test_point_plane_costs_inside_colmap_bundle_adjuster(core):
    rng = np.random.default_rng(7)
    pixel_noise = 0.5

    # Control: COLMAP's bundle adjustment alone leaves the planar points scattered off the plane.
    control, planar, (normal, offset), truth = _planar_scene(seed=5, pixel_noise=pixel_noise)
    summary = _adjuster(control).solve()
    assert summary.is_solution_usable()
    control_rms = _best_fit_plane_rms(np.array([control.points3D[i].xyz for i in planar]))
    control_errors = [np.linalg.norm(control.points3D[i].xyz - truth[i]) for i in planar]

    reconstruction, planar, (normal, offset), truth = _planar_scene(seed=5, pixel_noise=pixel_noise)
    # Perturb the planar points and start from a wrong plane (3 deg, 10 cm).
    for point_id in planar:
        reconstruction.points3D[point_id].xyz += rng.normal(scale=0.05, size=3)
    axis = np.cross(normal, [1.0, 0.0, 0.0])
    wrong_normal = pycolmap.Rotation3d(axis / np.linalg.norm(axis) * np.deg2rad(3.0)) * normal
    # Hold the adjuster and its problem: pyceres keeps the costs alive only as long as the
    # Python problem they were added through (adjust.problem.HybridProblem does the same).
    adjuster = _adjuster(reconstruction)
    problem = adjuster.problem
    num_blocks = problem.num_parameter_blocks()
    num_residuals = problem.num_residual_blocks()

    plane_normal = np.array(wrong_normal, dtype=np.float64)
    plane_offset = np.array([offset + 0.1], dtype=np.float64)
    problem.add_parameter_block(plane_normal, 3)
    problem.set_manifold(plane_normal, pyceres.SphereManifold(3))
    problem.add_parameter_block(plane_offset, 1)
    assert problem.parameter_block_tangent_size(plane_normal) == 2  # on the sphere
    sigma = 1e-4  # scene units (~1); tighter than the ~1 mm scatter from the pixel noise
    costs = []
    for point_id in planar:
        block = reconstruction.points3D[point_id].xyz  # a view: COLMAP's own block
        assert problem.has_parameter_block(block)
        costs.append(core.PointPlaneDistanceCost(sigma))
        problem.add_residual_block(costs[-1], None, [block, plane_normal, plane_offset])
    # The points were COLMAP's blocks already: only the two plane blocks are new.
    assert problem.num_parameter_blocks() == num_blocks + 2
    assert problem.num_residual_blocks() == num_residuals + len(planar)

    summary = adjuster.solve()
    assert summary.is_solution_usable()

    norm = np.linalg.norm(plane_normal)
    estimated = np.concatenate([plane_normal / norm, plane_offset / norm])
    if estimated[:3] @ normal < 0:
        estimated = -estimated
    angle = np.degrees(np.arccos(np.clip(estimated[:3] @ normal, -1.0, 1.0)))
    assert angle < 0.1
    assert abs(estimated[3] - offset) < 0.01

    # Points are pulled onto the plane, much closer than COLMAP alone puts them ...
    hybrid_rms = np.sqrt(np.mean(_off_plane(reconstruction, planar, *np.split(estimated, [3])) ** 2))
    assert hybrid_rms < 0.2 * control_rms
    # ... and back near the truth after the 5 cm perturbation, at least as close as COLMAP
    # alone gets them (the plane adds true information).
    errors = [np.linalg.norm(reconstruction.points3D[i].xyz - truth[i]) for i in planar]
    print(f"plane angle {angle:.4f} deg, offset error {abs(estimated[3] - offset):.5f}, "
          f"off-plane rms {hybrid_rms:.2e} (control {control_rms:.2e}), point error rms "
          f"{np.sqrt(np.mean(np.square(errors))):.4f} (control "
          f"{np.sqrt(np.mean(np.square(control_errors))):.4f}), max {max(errors):.4f}")
    assert np.sqrt(np.mean(np.square(errors))) < 0.01
    assert np.sqrt(np.mean(np.square(errors))) <= np.sqrt(np.mean(np.square(control_errors)))
    assert max(errors) < 0.03


def test_baseline_length_prior_closed_form_and_jacobians(core):
    rng = np.random.default_rng(4)
    for _ in range(5):
        a, b = random_pose(rng), random_pose(rng)
        in_a, in_b = rng.normal(scale=0.5, size=3), rng.normal(scale=0.5, size=3)
        cost = core.BaselineLengthPriorCost(12.0, 0.05, in_a, in_b)
        assert cost.parameter_block_sizes() == [POSE_BLOCK_SIZE] * 2
        blocks = [np.array(a.params), np.array(b.params)]
        residuals, jacobians = evaluate(cost, *blocks)
        length = np.linalg.norm(a.inverse() * in_a - b.inverse() * in_b)
        np.testing.assert_allclose(residuals, [(length - 12.0) / 0.05], atol=1e-9)
        for analytic, numeric in zip(jacobians, numeric_jacobians(cost, blocks)):
            np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError):
        core.BaselineLengthPriorCost(1.0, 0.0)


# ---------------------------------------------------------------- linear conditions on points


def test_linear_points_condition_closed_form_and_jacobians(core):
    rng = np.random.default_rng(5)
    matrix = rng.normal(size=(7, 9))
    reference = rng.normal(size=9)
    points = [rng.normal(size=3) for _ in range(3)]
    cost = core.LinearPointsConditionCost(matrix, reference)
    residuals, jacobians = evaluate(cost, *points)
    np.testing.assert_allclose(residuals, matrix @ (np.concatenate(points) - reference),
                               atol=1e-12)
    for k, (analytic, numeric) in enumerate(zip(jacobians, numeric_jacobians(cost, points))):
        np.testing.assert_allclose(analytic, matrix[:, 3 * k:3 * k + 3], atol=1e-12)
        np.testing.assert_allclose(analytic, numeric, atol=1e-6)


@pytest.mark.parametrize("shape", [(0, 6), (3, 5), (3, 0)])
def test_linear_points_condition_rejects_bad_shapes(core, shape):
    with pytest.raises(ValueError):
        core.LinearPointsConditionCost(np.ones(shape), np.zeros(shape[1]))
    with pytest.raises(ValueError):
        core.LinearPointsConditionCost(np.ones((2, 6)), np.zeros(5))
