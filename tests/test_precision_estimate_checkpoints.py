"""Check point precision and the generalisation-aware stochastic model.

- the check points' marginal covariance (precision.checkpoint_cofactors: their image observations
  eliminated in the normal system of the adjustment, Woodbury) equals the dense inverse of the
  normal matrix of the same problem with the check points added as 3D points with COLMAP's own
  reprojection residuals;
- with systematic plane offsets in the model (simulate_scene.perturb_planes), the classical
  stochastic model's Delta/sigma is far above 2, while the per-plane offsets with their prior
  (AdjustmentOptions.sigma_generalisation, consider parameters) bring it into a band around 1;
  the propagated sensitivity matches a re-solve with one plane moved; estimated offsets
  (generalisation_offsets=True) recover the plane shifts;
- the Delta/sigma table (evaluate.delta_sigma_table) and the Helmert residual sigmas.
"""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.adjust.problem import HybridProblem
from colmap_citymodel.assign.schedule import assign
from colmap_citymodel.block.priors import GNSSPriors
from colmap_citymodel.block.reconstruction import tie_points
from colmap_citymodel.options import AdjustmentOptions, AssignmentOptions
from colmap_citymodel.precision.checkpoints import delta_sigma_table, evaluate_with_precision, helmert_design_matrix, helmert_residual_sigmas, helmert_transform
from colmap_citymodel.precision.estimate import checkpoint_cofactors, cofactors, estimate_precision, precision_after_refine, whitened_jacobian
from colmap_citymodel.simulate.scene import ModelErrorOptions, perturb_planes
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene


def _checkpoints(truth: pycolmap.Reconstruction, num: int, rng, noise_px: float = 1.0):
    """Check points at the true positions of `num` tie points, observed anew (1 px noise) in the
    images that see them; returns ({id: xyz}, observations, the tie point ids used)."""
    candidates = [i for i in truth.point3D_ids() if truth.point3D(i).track.length() >= 4]
    chosen = rng.choice(candidates, num, replace=False)
    points, observations = {}, []
    for k, point_id in enumerate(chosen):
        xyz = truth.point3D(int(point_id)).xyz.copy()
        name = f"cp{k}"
        points[name] = xyz
        for element in truth.point3D(int(point_id)).track.elements:
            image = truth.image(element.image_id)
            uv = np.asarray(image.camera.img_from_cam((image.cam_from_world() * xyz)[None]))
            uv = uv.reshape(2) + rng.normal(0.0, noise_px, 2)
            observations.append((image.name, name, float(uv[0]), float(uv[1])))
    return points, observations, set(int(i) for i in chosen)


def _with_checkpoints(rec: pycolmap.Reconstruction, points, observations):
    """A copy of `rec` (single camera, trivial rigs) in which the check points are ordinary 3D
    points with their observations: COLMAP's bundle adjuster then adds their reprojection
    residuals itself. Tie point ids are kept (added in id order)."""
    out = pycolmap.Reconstruction()
    for camera in rec.cameras.values():
        out.add_camera_with_trivial_rig(camera)
    extra: dict[int, list] = {}
    for name, point_id, x, y in observations:
        image = next(im for im in rec.images.values() if im.name == name)
        extra.setdefault(image.image_id, []).append((point_id, x, y))
    elements: dict[str, list] = {}
    for image_id in sorted(rec.images):
        image = rec.image(image_id)
        keypoints = [p.xy for p in image.points2D]
        for point_id, x, y in extra.get(image_id, []):
            elements.setdefault(point_id, []).append(
                pycolmap.TrackElement(image_id, len(keypoints)))
            keypoints.append(np.array([x, y]))
        new = pycolmap.Image(name=image.name, keypoints=np.array(keypoints),
                             camera_id=image.camera_id, image_id=image_id)
        out.add_image_with_trivial_frame(new, image.cam_from_world())
    for point_id in sorted(rec.point3D_ids()):
        point = rec.point3D(point_id)
        assert out.add_point3D(point.xyz, pycolmap.Track(point.track.elements)) == point_id
    ids = {}
    for name in sorted(points):
        ids[name] = out.add_point3D(points[name], pycolmap.Track(elements[name]))
    return out, ids


GNSS_SIGMA = np.array([0.5, 0.5, 0.8])


def test_checkpoint_covariance_equals_the_dense_inverse_with_the_checkpoints_as_points():
    scene = make_street_scene(StreetSceneOptions(num_stations=4, point_spacing=2.5,
                                                 image_noise_px=1.0, seed=3))
    truth = scene.truth
    rng = np.random.default_rng(3)
    points, observations, used = _checkpoints(truth, 5, rng)
    ids = np.array(truth.reg_image_ids())
    centres = np.array([truth.image(i).projection_center() for i in ids])
    priors = GNSSPriors(ids, centres + rng.normal(size=centres.shape) * GNSS_SIGMA,
                        np.tile(GNSS_SIGMA, (len(ids), 1)))
    point_ids, xyz = tie_points(truth, exclude=used)
    assignment = assign(xyz, point_ids, scene.store, 0.5,
                        AssignmentOptions(min_points_per_plane=5))
    # sigma_image 0.8 px: the whitening of our Jacobians and of COLMAP's must agree.
    # The plane offsets as unknowns with sigma_generalisation's prior, beside every tie point
    # alike (the faces' own offsets and tilts would take their place).
    options = AdjustmentOptions(sigma_image=0.8, sigma_dtp=0.05, sigma_generalisation=0.1,
                                face_weighting="per_point")
    # Same state for both problems (no solve): the same linearisation point.
    without = HybridProblem(pycolmap.Reconstruction(truth), scene.store, assignment, priors,
                            options, robust_images=False, robust_planes=False,
                            generalisation_offsets=True)
    assert without.counts["gen"] == len(assignment.faces) >= 5
    rec_with, cp_ids = _with_checkpoints(truth, points, observations)
    with_cps = HybridProblem(rec_with, scene.store, assignment, priors, options,
                             robust_images=False, robust_planes=False,
                             generalisation_offsets=True)
    assert with_cps.counts["image"] == without.counts["image"] + 2 * len(observations)

    cof = cofactors(without, redundancy=False)
    result = checkpoint_cofactors(without, cof, points, observations)
    assert result.joint and result.ids == sorted(points)
    jacobian, layout = whitened_jacobian(with_cps)
    dense = jacobian.toarray()
    q = np.linalg.inv(dense.T @ dense)
    nc = layout.num_c
    column = {int(p): nc + 3 * k for k, p in enumerate(layout.point_ids)}
    index = np.concatenate([column[cp_ids[name]] + np.arange(3) for name in result.ids])
    expected = q[np.ix_(index, index)]
    np.testing.assert_allclose(result.q, expected, rtol=2e-4, atol=1e-6 * np.abs(expected).max())
    # Conditional (poses, planes held fixed) is smaller than marginal, and equals W^-1.
    for k, name in enumerate(result.ids):
        rows = slice(column[cp_ids[name]], column[cp_ids[name]] + 3)
        w = dense[:, rows].T @ dense[:, rows]
        np.testing.assert_allclose(result.q_conditional[k], np.linalg.inv(w), rtol=1e-4)
        marginal = result.q[3 * k:3 * k + 3, 3 * k:3 * k + 3]
        assert np.all(np.linalg.eigvalsh(marginal - result.q_conditional[k]) > -1e-12)


def _street(seed: int, shift_sigma: float = 0.2, offsets: bool = False,
            precision_options=None, face_weighting: str = "per_point"):
    """A 30-image street whose LOD2 model has per-plane shifts N(0, shift_sigma) along the
    normals (no tilts); truth poses as initial values, GNSS with a 1 m bias stated as 3/3/5 m.
    One hybrid solve (classical, or with estimated offsets), then Delta of 25 check points and
    their sigma under the classical and the generalisation-aware stochastic model. With
    `precision_options`, the precision refine() computes with them and no a priori
    sigma_generalisation."""
    scene = make_street_scene(StreetSceneOptions(num_stations=10, point_spacing=1.0,
                                                 image_noise_px=0.5, relief_sigma=0.03,
                                                 clutter_fraction=0.0, seed=seed))
    model = perturb_planes(scene.store, ModelErrorOptions(shift_sigma=shift_sigma,
                                                          rotation_sigma_deg=0.0), seed)
    truth = scene.truth
    rng = np.random.default_rng(seed)
    points, observations, used = _checkpoints(truth, 25, rng)
    ids = np.array(truth.reg_image_ids())
    centres = np.array([truth.image(i).projection_center() for i in ids])
    gnss = centres + [1.0, -1.0, 1.0] + rng.normal(size=centres.shape) * [0.3, 0.3, 0.5]
    priors = GNSSPriors(ids, gnss, np.tile([3.0, 3.0, 5.0], (len(ids), 1)))
    point_ids, xyz = tie_points(truth, exclude=used)
    assignment = assign(xyz, point_ids, model, 0.6, AssignmentOptions(min_points_per_plane=5))
    # Unger's sigma_dTP (0.2 m); the plane shifts are the generalisation error.
    # With the faces' errors as unknowns their prior is sigma_face (0.2 m), no other.
    options = AdjustmentOptions(sigma_dtp=0.2, sigma_generalisation=(
        shift_sigma if precision_options is None and face_weighting != "offsets" else None),
        face_weighting=face_weighting)
    problem = HybridProblem(pycolmap.Reconstruction(truth), model, assignment, priors, options,
                            robust_images=False, robust_planes=False,
                            generalisation_offsets=offsets)
    problem.solve()
    if precision_options is None:
        precision = estimate_precision(problem, checkpoint_observations=observations)
    else:
        precision = precision_after_refine(problem, precision_options, observations)
    evaluation = evaluate_with_precision(problem.reconstruction, points, observations,
                                         np.zeros(3), precision)
    return evaluation, precision, (scene.store, model, problem)


def _pooled_ratio(evaluations, model: str) -> np.ndarray:
    """Per axis RMS of Delta over RMS of sigma, pooled over several independent scenes."""
    delta = np.vstack([e.errors for e in evaluations])
    sigma = np.vstack([e.sigmas_of(model) for e in evaluations])
    return np.sqrt(np.mean(delta ** 2, 0)) / np.sqrt(np.mean(sigma ** 2, 0))


@pytest.fixture(scope="module")
def streets():
    return [_street(seed) for seed in (11, 12, 13)]


def test_classical_model_is_over_optimistic_and_per_plane_offsets_are_honest(streets):
    evaluations = [e for e, _, _ in streets]
    classical = _pooled_ratio(evaluations, "classical")
    aware = _pooled_ratio(evaluations, "generalisation_aware")
    # Independent f_dTP average the plane shifts away with the number of points: sigma_CP of a
    # few cm against decimetre Delta (Unger Table 12: 3 to 19; measured 3.3 / 4.3 / 5.9).
    assert np.all(classical > 3.0), classical
    # One shared offset per plane: the datum error of N shifted planes is in sigma_CP
    # (measured 1.0 / 0.9 / 1.2).
    assert np.all((aware > 0.5) & (aware < 2.0)), aware
    assert np.all(classical > 2.5 * aware)
    for evaluation, precision, _ in streets:
        assert precision.generalisation == "consider"
        # Same estimate, larger sigma: the consider part only adds.
        assert np.all(evaluation.sigmas_of("generalisation_aware")
                      > evaluation.sigmas_of("classical"))
        aware_points = np.sqrt(np.diagonal(precision.aware("point_cov"), axis1=1, axis2=2))
        assert np.median(aware_points) > 2 * np.median(precision.point_sigmas)
        assert precision.summary()["generalisation"]["mode"] == "consider"


def test_refine_states_generalisation_aware_sigmas_without_being_told_the_sigma():
    # What refine gives by default (no a priori sigma_generalisation): the covariances under
    # the generalisation-aware model with the sigma the planes' mean residuals give, honest
    # where the classical ones are not (measured: sigma 0.24 / 0.24 m from planes shifted by
    # N(0, 0.2 m); Delta/sigma 0.95 / 0.80 / 1.15 against 3.4 / 4.2 / 6.3); switched off, the
    # classical ones only.
    from colmap_citymodel.options import PrecisionOptions

    runs = [_street(seed, precision_options=PrecisionOptions(covariances="on"))
            for seed in (11, 12)]
    for _, precision, _ in runs:
        assert precision.generalisation == "consider"
        estimate = precision.generalisation_estimate
        assert estimate["sigma_prior_m"] is None and 0.1 < estimate["sigma_used_m"] < 0.35
    evaluations = [e for e, _, _ in runs]
    classical = _pooled_ratio(evaluations, "classical")
    aware = _pooled_ratio(evaluations, "generalisation_aware")
    assert np.all(classical > 3.0), classical
    assert np.all((aware > 0.5) & (aware < 2.0)), aware
    _, plain, _ = _street(11, precision_options=PrecisionOptions(
        covariances="on", generalisation_from_data=False))
    assert plain.generalisation == "none"


def test_generalisation_sigma_from_the_planes_mean_residuals(streets):
    # The variance component of the plane offsets (moments of the planes' mean f_dTP residuals,
    # generalisation_effects): the model's planes were shifted by N(0, 0.2 m) (measured
    # 0.24 / 0.24 / 0.26; vertices shared by neighbouring faces move them a bit more) ...
    for _, precision, _ in streets:
        estimate = precision.generalisation_estimate
        assert 0.15 < estimate["sigma_estimated_m"] < 0.35
        assert estimate["sigma_used_m"] == 0.2 and not estimate["estimated"]
    # ... and an unshifted model gives (almost) none, with or without an a priori value.
    _, precision, (_, _, problem) = _street(11, shift_sigma=1e-6)
    assert precision.generalisation_estimate["sigma_estimated_m"] < 0.02
    again = estimate_precision(problem, estimate_generalisation=True)
    assert again.generalisation == "consider"
    assert again.generalisation_sigma == pytest.approx(
        precision.generalisation_estimate["sigma_estimated_m"])


def _consider_street():
    """A noise-free street of 4 stations on its exact model, solved once, with the consider
    parameters' predicted responses of 6 check points: what re-solving with a changed model
    is compared with."""
    from colmap_citymodel.precision.checkpoints import triangulate_checkpoints
    from colmap_citymodel.precision.estimate import checkpoint_cofactors, generalisation_effects

    scene = make_street_scene(StreetSceneOptions(num_stations=4, point_spacing=2.5,
                                                 image_noise_px=0.0, relief_sigma=0.0,
                                                 clutter_fraction=0.0, seed=5))
    truth = scene.truth
    rng = np.random.default_rng(5)
    points, observations, used = _checkpoints(truth, 6, rng, noise_px=0.0)
    ids = np.array(truth.reg_image_ids())
    centres = np.array([truth.image(i).projection_center() for i in ids])
    priors = GNSSPriors(ids, centres, np.tile([3.0, 3.0, 5.0], (len(ids), 1)))
    point_ids, xyz = tie_points(truth, exclude=used)
    assignment = assign(xyz, point_ids, scene.store, 0.5,
                        AssignmentOptions(min_points_per_plane=5))
    options = AdjustmentOptions(sigma_dtp=0.05, sigma_generalisation=0.2)
    problem = HybridProblem(pycolmap.Reconstruction(truth), scene.store, assignment, priors,
                            options, robust_images=False, robust_planes=False)
    problem.solve()
    cof = cofactors(problem, keep_system=True)
    effects = generalisation_effects(problem, cof, 0.2)
    cps = checkpoint_cofactors(problem, cof, points, observations)
    before = triangulate_checkpoints(problem.reconstruction, observations)

    def resolved_change(store):
        """The check points' change when the same problem is solved again on `store`."""
        again = HybridProblem(pycolmap.Reconstruction(problem.reconstruction), store,
                              assignment, priors, options, robust_images=False,
                              robust_planes=False)
        again.solve()
        after = triangulate_checkpoints(again.reconstruction, observations)
        return np.concatenate([after[i] - before[i] for i in cps.ids])

    return scene, problem, effects, cps.b @ effects.camera, resolved_change


def test_consider_covariance_is_the_spread_of_the_estimate_over_plane_offsets():
    # The linear propagation of per-plane offsets must match what re-solving does: offset one
    # plane's f_dTP observations by 0.3 m (shift its tie points' plane by moving the plane in
    # the model) and compare the change of the check points with the predicted sensitivity.
    scene, problem, _, predicted, resolved_change = _consider_street()
    # predicted: (3N, 3F), the first F columns the check points' change per metre of offset
    # The largest plane: move its true surface by +0.3 m, i.e. the observed distances of its
    # tie points become -0.3 m: emulate by moving the model face (vertices) by -0.3 m along n.
    k = int(np.argmax(np.bincount(problem.point_faces, minlength=scene.store.num_faces)
                      [problem.blocks.faces]))
    face = int(problem.blocks.faces[k])
    moved = scene.store.vertices.copy()
    normal = scene.store.normals[face]
    moved[scene.store.face_vertex_ids(face)] -= 0.3 * normal
    change = resolved_change(scene.store.with_vertices(moved))
    # Moving the vertices also moves the neighbouring faces that share them (slightly, they are
    # re-fitted), so direction and size are compared (measured: 0.699 vs 0.698 m, cos 0.998).
    expected = -0.3 * predicted[:, k]
    assert np.linalg.norm(change) > 0.1
    assert np.linalg.norm(change) == pytest.approx(np.linalg.norm(expected), rel=0.1)
    cosine = change @ expected / np.linalg.norm(change) / np.linalg.norm(expected)
    assert abs(cosine) > 0.95


def test_estimated_offsets_recover_the_plane_shifts():
    evaluation, precision, (store, model, problem) = _street(11, offsets=True)
    assert precision.generalisation == "estimated"
    assert problem.counts["gen"] == len(problem.blocks.faces) >= 10
    # The true offset of each plane: the original face centroid's distance to the shifted
    # plane (n.X + d + o = 0 on the true surface, so o = -(n.C + d)).
    true = np.array([-(model.normals[f] @ store.centroids[f] + model.offsets[f])
                     for f in problem.blocks.faces])
    estimated = problem.blocks.generalisation_array
    assert np.corrcoef(true, estimated)[0, 1] > 0.8
    assert "generalisation_aware" in evaluation.covariances
    assert "classical" not in evaluation.covariances
    assert precision.summary()["generalisation_offsets"]["num_planes"] == len(estimated)


def test_check_point_sigmas_with_the_faces_errors_as_unknowns():
    """Each face's offset and tilts estimated with their prior (sigma_face 0.2 m, the planes'
    true shift sigma): the check points' sigmas are that model's own, stated with the prior
    they were estimated with, not scaled below it by a variance factor under 1, and cover the
    errors the shifted planes leave."""
    streets = [_street(seed, face_weighting="offsets") for seed in (11, 12, 13)]
    for evaluation, precision, _ in streets:
        assert precision.generalisation == "estimated"
        assert precision.generalisation_sigma == pytest.approx(0.2)
        assert "N(0, 0.200^2 m^2)" in evaluation.sigma_notes["generalisation_aware"]
    # The streets' images fit at half their stated sigma (s0 0.49): scaled by s0 the sigmas
    # were up to 1.8x optimistic in Z (Delta / sigma 1.27 / 1.29 / 1.79).
    ratio = _pooled_ratio([e for e, _, _ in streets], "generalisation_aware")
    assert np.all((ratio > 0.4) & (ratio < 1.3)), ratio


def test_delta_sigma_table_in_the_evaluation(streets):
    evaluation, _, _ = streets[0]
    for model in ("classical", "generalisation_aware"):
        table = evaluation.delta_sigma(model)
        sigmas = evaluation.sigmas_of(model)
        assert table["num_checkpoints"] == len(evaluation.ids) == 25
        for k, axis in enumerate("XYZ"):
            row = table["before_helmert"][axis]
            assert row["rms_delta"] == pytest.approx(
                np.sqrt(np.mean(evaluation.errors[:, k] ** 2)))
            assert row["rms_sigma"] == pytest.approx(np.sqrt(np.mean(sigmas[:, k] ** 2)))
            assert row["ratio"] == pytest.approx(row["rms_delta"] / row["rms_sigma"])
            after = table["after_helmert"][axis]
            assert after["rms_sigma"] == row["rms_sigma"]  # Unger Table 13: the same sigma_CP
            # The Helmert transform removes the datum part of the covariance too.
            assert after["rms_sigma_residual"] < after["rms_sigma"]
    d = evaluation.todict()
    assert set(d["delta_sigma_by_model"]) == {"classical", "generalisation_aware"}
    assert d["delta_sigma_by_model"]["classical"]["before_helmert"]["Z"]["ratio"] == \
        pytest.approx(evaluation.delta_sigma("classical")["before_helmert"]["Z"]["ratio"])
    # The honest sigma is the primary one (checkpoint_plots plots points[id]["sigma"]).
    assert d["sigma_model"] == "generalisation_aware"
    assert d["delta_sigma"]["model"] == "generalisation_aware"
    np.testing.assert_allclose(d["points"]["cp0"]["sigma"],
                               d["points"]["cp0"]["sigma_generalisation_aware"])
    assert len(d["points"]["cp0"]["sigma_classical"]) == 3
    assert evaluation.summary().count("stochastic model (Unger Tables 12/13") == 2


def test_helmert_residual_sigmas():
    rng = np.random.default_rng(0)
    points = rng.uniform(-20, 20, (12, 3)) + [691000.0, 5336000.0, 520.0]
    a = helmert_design_matrix(points)
    # The design matrix is the derivative of helmert_transform's similarity.
    step = np.array([0.01, -0.02, 0.03, 1e-4, -2e-4, 3e-4, 5e-5])
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_rotvec(step[3:6]).as_matrix()
    centre = points.mean(0)
    moved = centre + step[:3] + (1 + step[6]) * (points - centre) @ rotation.T
    np.testing.assert_allclose((moved - points).ravel(), a @ step, atol=2e-6)
    # A covariance that is purely a common shift (datum) disappears after the Helmert fit ...
    shift = np.kron(np.ones((12, 12)), np.diag([0.04, 0.01, 0.09]))
    assert np.abs(helmert_residual_sigmas(points, shift)).max() < 1e-7
    # ... independent noise mostly stays (7 of 36 degrees of freedom are fitted).
    white = np.eye(36) * 0.01 ** 2
    sigma = helmert_residual_sigmas(points, white)
    assert 0.7 * 0.01 < np.sqrt(np.mean(sigma ** 2)) < 0.01
    # Monte Carlo: RMS of actual Helmert residuals of noisy points matches the prediction.
    known = points.copy()
    residuals = [helmert_transform(known, known + rng.normal(0, 0.01, known.shape)).residuals
                 for _ in range(400)]
    np.testing.assert_allclose(np.sqrt(np.mean(np.square(residuals), axis=(0, 1))),
                               np.sqrt(np.mean(sigma ** 2, 0)), rtol=0.08)


def test_delta_sigma_table_by_hand():
    errors = np.array([[0.1, 0.0, -0.2], [-0.1, 0.0, 0.2]])
    sigmas = np.array([[0.05, 0.01, 0.1], [0.05, 0.01, 0.1]])
    table = delta_sigma_table(errors, sigmas)
    assert table["before_helmert"]["X"] == pytest.approx(
        {"rms_delta": 0.1, "rms_sigma": 0.05, "ratio": 2.0})
    assert table["before_helmert"]["Y"]["ratio"] == 0.0
    assert table["before_helmert"]["Z"]["ratio"] == pytest.approx(2.0)
    assert "after_helmert" not in table


def test_consider_covariance_follows_a_tilted_plane_as_re_solving_does():
    # The tilt consider parameters, checked like the offsets above: tilt the largest plane of
    # the model about its principal tilt axis (its vertices rotated about their centroid) and
    # compare the check points' change on re-solving with the predicted response.
    from colmap_citymodel.adjust.observability import face_tilts

    scene, problem, effects, predicted, resolved_change = _consider_street()
    num_faces = len(problem.blocks.faces)
    assert effects.camera.shape[1] == 3 * num_faces
    k = int(np.argmax(np.bincount(problem.point_faces, minlength=scene.store.num_faces)
                      [problem.blocks.faces]))
    face = int(problem.blocks.faces[k])
    tilt = face_tilts(scene.store, [face], 1.0)[face]
    values, vectors = np.linalg.eigh(tilt.covariance)
    # The face's larger principal tilt (column F + 2k + 1: eigh sorts ascending), 1 deg.
    angle = np.radians(1.0)
    direction = vectors[:, 1] @ tilt.axes  # in the face: its points move by angle * lever
    normal = scene.store.normals[face]
    moved = scene.store.vertices.copy()
    corners = scene.store.face_vertex_ids(face)
    moved[corners] += angle * ((moved[corners] - tilt.centroid) @ direction)[:, None] * normal
    change = resolved_change(scene.store.with_vertices(moved))
    # The model plane tilted by +angle: its tie points' observed distances change as a true
    # surface tilted by -angle would; the column is per sqrt(eigenvalue) of that tilt
    # (measured: 0.0357 vs 0.0346 m, cos 0.978).
    expected = -angle / np.sqrt(values[1]) * predicted[:, num_faces + 2 * k + 1]
    assert np.linalg.norm(change) > 0.02
    assert np.linalg.norm(change) == pytest.approx(np.linalg.norm(expected), rel=0.15)
    cosine = change @ expected / np.linalg.norm(change) / np.linalg.norm(expected)
    assert abs(cosine) > 0.9


def test_projection_jacobians_with_refined_intrinsics():
    """The check points' Jacobian by the camera's parameters (intrinsics refined): for a
    pinhole camera d(x)/d(fx) = X/Z and d(y)/d(fy) = Y/Z."""
    from colmap_citymodel.precision.estimate import _projection_jacobians
    from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene

    rec = make_street_scene(StreetSceneOptions(seed=3, num_stations=4)).truth
    point = next(iter(rec.points3D.values()))
    image = rec.image(point.track.elements[0].image_id)
    _, _, j_camera = _projection_jacobians(rec, image, point.xyz, np.array([0, 1]))
    x, y, z = image.cam_from_world() * point.xyz
    np.testing.assert_allclose(j_camera, [[x / z, 0.0], [0.0, y / z]], rtol=1e-5, atol=1e-9)
