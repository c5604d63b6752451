"""A posteriori precision: variance factors, global test and covariances against dense algebra.

The tiny problems here are a linear model solved with numpy and a 12-image piece of the
synthetic street (truth poses, image noise of 1 px, GNSS drawn with exactly its stated sigmas),
so that "correctly weighted" is known and the dense normal matrix is small enough to invert.
"""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.adjust.problem import GROUPS, HybridProblem
from colmap_citymodel.assign.schedule import assign
from colmap_citymodel.block.priors import GNSSPriors
from colmap_citymodel.block.reconstruction import tie_points
from colmap_citymodel.options import AdjustmentOptions, AssignmentOptions
from colmap_citymodel.precision.estimate import PHOTOGRAMMETRIC_FLIP, cofactors, estimate_precision, global_test, image_jacobian, omega_phi_kappa, variance_factors, whitened_jacobian
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene

GNSS_SIGMA = np.array([0.5, 0.5, 0.8])


# -- linear model: everything in closed form -----------------------------------------------------

def _linear_problem(seed: int, sigma_true: float, sigma_stated: float, n: int = 60, u: int = 4):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, u))
    x = rng.normal(size=u)
    sigmas = np.where(np.arange(n) < n // 2, 1.0, 0.1)  # two groups of very different sigma
    y = a @ x + rng.normal(size=n) * sigmas * sigma_true
    stated = sigmas * sigma_stated
    aw, yw = a / stated[:, None], y / stated
    estimate = np.linalg.lstsq(aw, yw, rcond=None)[0]
    v = aw @ estimate - yw
    hat = aw @ np.linalg.solve(aw.T @ aw, aw.T)
    return v, np.diag(hat), n // 2


def test_variance_factors_match_dense_least_squares():
    v, hat_diag, half = _linear_problem(seed=1, sigma_true=1.0, sigma_stated=1.0)
    residuals = {"a": v[:half], "b": v[half:]}
    redundancy = {"a": float(np.sum(1 - hat_diag[:half])), "b": float(np.sum(1 - hat_diag[half:]))}
    exact = variance_factors(residuals, 4, redundancy)
    assert exact.method == "hat_matrix"
    assert exact.redundancy == pytest.approx(60 - 4)
    assert exact.sigma0_squared == pytest.approx(v @ v / 56)
    for g, r in redundancy.items():
        assert exact.sigma0_by_group[g] == pytest.approx(np.sqrt(np.sum(residuals[g] ** 2) / r))
    approx = variance_factors(residuals, 4)
    assert approx.method == "proportional"
    assert approx.sigma0_squared == pytest.approx(exact.sigma0_squared)
    assert approx.redundancy_by_group == {"a": 28.0, "b": 28.0}


def test_global_test_accepts_right_sigmas_and_rejects_sigmas_off_by_three():
    accepted = []
    for seed in range(200):
        v, _, _ = _linear_problem(seed, sigma_true=1.0, sigma_stated=1.0)
        accepted.append(global_test(v @ v, 56).accepted)
    # alpha = 0.05: about 95 % of correctly weighted problems pass.
    assert 0.88 < np.mean(accepted) < 0.995
    for stated in (3.0, 1.0 / 3.0):  # pessimistic and optimistic sigmas both fail
        results = [global_test(v @ v, 56)
                   for v, _, _ in (_linear_problem(s, 1.0, stated) for s in range(50))]
        assert not any(t.accepted for t in results)
        assert max(t.p_value for t in results) < 0.05


def test_global_test_numbers():
    test = global_test(100.0, 100)
    assert test.accepted and test.p_value == pytest.approx(0.96, abs=0.02)
    assert test.lower < 100 < test.upper
    with pytest.raises(ValueError):
        global_test(1.0, 0)


# -- a tiny bundle adjustment with a city model --------------------------------------------------

def _tiny(sigma_scale: float = 1.0, with_model: bool = True, seed: int = 3, holds=None,
          face_weighting: str = AdjustmentOptions.face_weighting):
    """12 images, ~230 points; image noise 1 px and GNSS noise of GNSS_SIGMA, so the stochastic
    model is right for sigma_scale = 1 (all stated sigmas multiplied by it)."""
    scene = make_street_scene(StreetSceneOptions(num_stations=4, point_spacing=2.5,
                                                 image_noise_px=1.0, seed=seed))
    rec = pycolmap.Reconstruction(scene.truth)
    rng = np.random.default_rng(seed)
    ids = np.array(rec.reg_image_ids())
    centres = np.array([rec.image(i).projection_center() for i in ids])
    priors = GNSSPriors(ids, centres + rng.normal(size=centres.shape) * GNSS_SIGMA,
                        np.tile(GNSS_SIGMA * sigma_scale, (len(ids), 1)))
    options = AdjustmentOptions(sigma_image=sigma_scale, sigma_dtp=0.03 * sigma_scale,
                                sigma_dvt=0.01 * sigma_scale, sigma_vt=0.01 * sigma_scale,
                                face_weighting=face_weighting)
    store = assignment = None
    if with_model:
        point_ids, xyz = tie_points(rec)
        store = scene.store
        assignment = assign(xyz, point_ids, store, 0.5, AssignmentOptions(min_points_per_plane=5))
    problem = HybridProblem(rec, store, assignment, priors, options, robust_images=False,
                            robust_planes=False, baselines=holds(rec) if holds else None)
    problem.solve()
    return problem


@pytest.fixture(scope="module")
def tiny():
    return _tiny()


def test_cofactors_equal_the_dense_inverse_of_the_normal_matrix(tiny):
    assert len(tiny.blocks.faces) >= 5 and len(tiny.blocks.vertex_ids) > 0
    cof = cofactors(tiny)
    jacobian, layout = whitened_jacobian(tiny)
    dense = jacobian.toarray()
    nc = layout.num_c
    assert dense.shape[1] == tiny.num_unknowns()
    q = np.linalg.inv(dense.T @ dense)
    np.testing.assert_allclose(cof.q_cc, q[:nc, :nc], rtol=1e-6, atol=1e-12 * np.abs(q).max())
    for k in range(len(layout.point_ids)):
        block = q[nc + 3 * k:nc + 3 * k + 3, nc + 3 * k:nc + 3 * k + 3]
        np.testing.assert_allclose(cof.q_points[k], block, rtol=1e-6, atol=1e-12)
    # Conditional = inverse of the point's own normal block.
    w = dense[:, nc:nc + 3].T @ dense[:, nc:nc + 3]
    np.testing.assert_allclose(cof.q_points_conditional[0], np.linalg.inv(w), rtol=1e-8)
    # Redundancy numbers r_i = 1 - (J Q J^T)_ii summed per group; they add up to n - u.
    r_i = 1.0 - np.sum((dense @ q) * dense, axis=1)
    start = 0
    for g in GROUPS:
        n = tiny.counts[g]
        assert cof.redundancy_by_group[g] == pytest.approx(r_i[start:start + n].sum(), abs=1e-6)
        start += n
    assert sum(cof.redundancy_by_group.values()) == pytest.approx(
        dense.shape[0] - dense.shape[1], abs=1e-6)
    assert cof.datum_defect == 0


def test_s0_equals_the_dense_least_squares_minimum(tiny):
    # Ceres stops on a relative cost tolerance; a dense Gauss-Newton step from its solution
    # finds the least-squares minimum of the linearised problem, whose v^T v / (n - u) must
    # equal our s0^2 (same model, same weights).
    jacobian, _ = whitened_jacobian(tiny)
    dense = jacobian.toarray()
    residuals = tiny.group_residuals()
    v = np.concatenate([residuals[g] for g in GROUPS])
    step = -np.linalg.solve(dense.T @ dense, dense.T @ v)
    v_min = v + dense @ step
    n, u = dense.shape
    precision = estimate_precision(tiny)
    assert precision.variance.redundancy == pytest.approx(n - u, abs=1e-6)
    assert precision.variance.sigma0_squared == pytest.approx(v_min @ v_min / (n - u), rel=1e-6)
    assert np.abs(step[:6]).max() < 1e-3  # Ceres' solution is (nearly) the minimum


def test_pycolmap_covariance_agrees_with_our_blocks_in_the_problem(tiny):
    # COLMAP's estimator still works with plane and vertex blocks (Schur structure kept):
    # same pose covariances; its point covariance is the conditional one.
    cov = pycolmap.estimate_ba_covariance_from_problem(pycolmap.BACovarianceOptions(),
                                                       tiny.reconstruction, tiny.problem)
    assert cov is not None
    cof = cofactors(tiny, redundancy=False)
    rec = tiny.reconstruction
    for image_id in rec.reg_image_ids():
        columns = cof.layout.columns("frame", rec.image(image_id).frame_id)
        ours = cof.q_cc[columns, columns]
        np.testing.assert_allclose(cov.get_cam_cov_from_world(image_id), ours, rtol=1e-5,
                                   atol=1e-9 * np.abs(ours).max())
    for k, point_id in enumerate(cof.layout.point_ids[:20]):
        np.testing.assert_allclose(cov.get_point_cov(int(point_id)),
                                   cof.q_points_conditional[k], rtol=1e-5)
        # Marginal >= conditional: the other unknowns' uncertainty adds to the point's.
        assert np.all(np.linalg.eigvalsh(cof.q_points[k] - cof.q_points_conditional[k]) > -1e-12)


def test_pose_tangent_convention_matches_ceres(tiny):
    # The GNSS rows observe the projection centre: their Jacobian w.r.t. the frame block must
    # equal the numerical derivative of X0 under our model of Ceres' pose manifold.
    jacobian, layout = whitened_jacobian(tiny)
    rec = tiny.reconstruction
    first_gnss = tiny.counts["image"]
    for k, image_id in enumerate(rec.reg_image_ids()[:4]):
        columns = layout.columns("frame", rec.image(image_id).frame_id)
        rows = jacobian[first_gnss + 3 * k:first_gnss + 3 * k + 3, columns].toarray()
        numeric = image_jacobian(rec, image_id)[:3] / GNSS_SIGMA[:, None]
        np.testing.assert_allclose(rows, numeric, rtol=1e-5, atol=1e-6)


def _synthetic_ba(sigma_scale: float, seed: int = 5) -> HybridProblem:
    """pycolmap's synthetic dataset (10 images around 150 points), image noise 1 px, GNSS drawn
    with sigma (0.1, 0.1, 0.15) (scene ~8 units across); stated sigmas x sigma_scale."""
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs, options.num_cameras_per_rig, options.num_frames_per_rig = 1, 1, 10
    options.num_points3D = 150
    pycolmap.set_random_seed(seed)
    rec = pycolmap.synthesize_dataset(options)
    ids = np.array(rec.reg_image_ids())
    centres = np.array([rec.image(i).projection_center() for i in ids])
    noise = pycolmap.SyntheticNoiseOptions()
    noise.point2D_stddev = 1.0
    pycolmap.synthesize_noise(noise, rec)
    sigma = np.array([0.1, 0.1, 0.15])
    rng = np.random.default_rng(seed)
    priors = GNSSPriors(ids, centres + rng.normal(size=centres.shape) * sigma,
                        np.tile(sigma * sigma_scale, (len(ids), 1)))
    problem = HybridProblem(rec, None, None, priors, AdjustmentOptions(sigma_image=sigma_scale),
                            robust_images=False, robust_planes=False)
    problem.solve()
    return problem


def test_global_test_on_a_bundle_adjustment():
    right = estimate_precision(_synthetic_ba(1.0))
    assert right.variance.test.accepted
    assert 0.9 < right.variance.sigma0 < 1.1
    for scale in (3.0, 1.0 / 3.0):
        wrong = estimate_precision(_synthetic_ba(scale))
        assert not wrong.variance.test.accepted
        assert wrong.variance.test.p_value < 1e-6
        assert wrong.variance.sigma0 == pytest.approx(1.0 / scale, rel=0.1)
        # Covariances are scaled by s0^2: the same whatever the stated sigma scale.
        np.testing.assert_allclose(np.median(wrong.point_sigmas, 0),
                                   np.median(right.point_sigmas, 0), rtol=0.01)


def test_precision_of_images_and_points():
    # Every tie point alike: the exact planes (sigma_dTP 0.03 m) hold the block's rotation too.
    # With the faces' offsets and tilts free by their 0.2 m prior, GNSS alone holds it.
    alike = _tiny(face_weighting="per_point")
    precision = estimate_precision(alike)
    rec = alike.reconstruction
    assert len(precision.image_ids) == rec.num_reg_images()
    assert len(precision.point_ids) == rec.num_points3D()
    sigma = precision.image_sigmas
    # GNSS at 0.5 m and 1 px images over ~20 m: centimetre centres, small angles.
    assert np.all(sigma[:, :3] > 1e-4) and np.all(sigma[:, :3] < 0.5)
    assert np.all(sigma[:, 3:] > 1e-4) and np.all(sigma[:, 3:] < 1.0)
    np.testing.assert_allclose(precision.centres[0],
                               rec.image(int(precision.image_ids[0])).projection_center())
    assert np.all(precision.point_sigmas >= precision.point_sigmas_conditional - 1e-12)
    free = estimate_precision(_tiny()).image_sigmas
    assert np.median(free[:, 3:]) > 2 * np.median(sigma[:, 3:])
    summary = precision.summary()
    assert summary["redundancy_method"] == "hat_matrix" and summary["covariances"]


def test_variance_only_uses_the_proportional_redundancy(tiny):
    quick = estimate_precision(tiny, covariances=False)
    full = estimate_precision(tiny)
    assert not quick.has_covariances and quick.variance.method == "proportional"
    assert quick.variance.sigma0 == pytest.approx(full.variance.sigma0)
    assert quick.variance.redundancy == pytest.approx(full.variance.redundancy)


def test_omega_phi_kappa_convention():
    # A nadir camera whose image top points north has omega = phi = kappa = 0.
    nadir = pycolmap.Rigid3d(pycolmap.Rotation3d(PHOTOGRAMMETRIC_FLIP.copy()), np.zeros(3))
    np.testing.assert_allclose(omega_phi_kappa(nadir), 0.0, atol=1e-12)
    omega, phi, kappa = np.radians([10.0, -20.0, 30.0])
    rx = np.array([[1, 0, 0], [0, np.cos(omega), -np.sin(omega)],
                   [0, np.sin(omega), np.cos(omega)]])
    ry = np.array([[np.cos(phi), 0, np.sin(phi)], [0, 1, 0], [-np.sin(phi), 0, np.cos(phi)]])
    rz = np.array([[np.cos(kappa), -np.sin(kappa), 0], [np.sin(kappa), np.cos(kappa), 0],
                   [0, 0, 1]])
    world_from_photo = rx @ ry @ rz
    cam_from_world = (world_from_photo @ PHOTOGRAMMETRIC_FLIP).T
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_world), np.zeros(3))
    np.testing.assert_allclose(omega_phi_kappa(pose), [omega, phi, kappa], atol=1e-10)


def test_variance_components_recover_the_true_sigmas():
    # Relief of 3 cm off the planes (no clutter), image noise 1 px, GNSS noise GNSS_SIGMA; the
    # stated sigmas are sigma_dTP 0.2 m (generalised preset) and GNSS 3x too large.
    from colmap_citymodel.precision.variance_components import estimate_variance_components

    scene = make_street_scene(StreetSceneOptions(num_stations=4, point_spacing=1.5,
                                                 image_noise_px=1.0, relief_sigma=0.03,
                                                 clutter_fraction=0.0, seed=4))
    truth = scene.truth
    rng = np.random.default_rng(4)
    ids = np.array(truth.reg_image_ids())
    centres = np.array([truth.image(i).projection_center() for i in ids])
    observed = centres + rng.normal(size=centres.shape) * GNSS_SIGMA
    point_ids, xyz = tie_points(truth)
    assignment = assign(xyz, point_ids, scene.store, 0.5, AssignmentOptions(min_points_per_plane=5))
    stated = AdjustmentOptions(sigma_dtp=0.2)

    def build(factors):
        options = AdjustmentOptions(sigma_dtp=0.2 * factors["dTP"],
                                    sigma_dvt=0.01 * factors["dVT"], sigma_vt=0.01 * factors["VT"])
        priors = GNSSPriors(ids, observed, np.tile(3 * GNSS_SIGMA * factors["gnss"], (len(ids), 1)))
        return HybridProblem(pycolmap.Reconstruction(truth), scene.store, assignment, priors,
                             options, robust_images=False, robust_planes=False)

    vce = estimate_variance_components(build, {"image": 1.0, "gnss": 1.0, "dTP": stated.sigma_dtp})
    assert vce.converged and len(vce.history) <= 15
    assert vce.factors["image"] == pytest.approx(1.0, abs=0.05)
    assert vce.factors["gnss"] == pytest.approx(1 / 3, rel=0.35)  # 36 GNSS observations only
    assert vce.sigmas["dTP"] == pytest.approx(0.03, rel=0.15)
    # With the estimated sigmas the global test accepts the model.
    assert vce.precision.variance.test.accepted
