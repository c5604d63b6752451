"""ceres_blocks: our residuals reach the very parameter blocks of COLMAP's bundle adjuster."""

from __future__ import annotations

import gc

import numpy as np
import pycolmap
import pytest

from colmap_citymodel import _ext, ceres_blocks


@pytest.fixture(scope="module")
def core():
    return _ext.load_core()


def _scene(num_cameras_per_rig: int = 1, seed: int = 11) -> pycolmap.Reconstruction:
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs = 1
    options.num_cameras_per_rig = num_cameras_per_rig
    options.num_frames_per_rig = 5
    options.num_points3D = 40
    pycolmap.set_random_seed(seed)
    return pycolmap.synthesize_dataset(options)


def _adjuster(reconstruction, gauge=pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD):
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.images:
        config.add_image(image_id)
    config.fix_gauge(gauge)
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.refine_focal_length = False
    options.refine_extra_params = False
    return pycolmap.create_default_ceres_bundle_adjuster(options, config, reconstruction)


def test_point_block_is_the_problem_block_and_writes_through():
    reconstruction = _scene()
    problem = _adjuster(reconstruction).problem
    num_blocks = problem.num_parameter_blocks()
    for point_id in reconstruction.points3D:
        block = ceres_blocks.point_block(reconstruction, point_id)
        assert block.shape == (3,) and block.dtype == np.float64
        assert problem.has_parameter_block(block)
        assert ceres_blocks.is_variable_block(problem, block)
        assert problem.parameter_block_size(block) == 3
    # A copy is not a block: our residual on a copy would be a new unknown.
    assert not problem.has_parameter_block(block.copy())
    block[:] = [1.0, 2.0, 3.0]
    np.testing.assert_array_equal(reconstruction.points3D[point_id].xyz, [1.0, 2.0, 3.0])
    assert problem.num_parameter_blocks() == num_blocks


def test_frame_pose_block_layout_and_gauge():
    reconstruction = _scene()
    problem = _adjuster(reconstruction).problem
    tangent_sizes = []
    for frame_id, frame in reconstruction.frames.items():
        block = ceres_blocks.frame_pose_block(reconstruction, frame_id)
        assert block.shape == (ceres_blocks.POSE_BLOCK_SIZE,)
        assert problem.has_parameter_block(block)
        np.testing.assert_allclose(block[:4], frame.rig_from_world.rotation.quat)
        np.testing.assert_allclose(block[4:], frame.rig_from_world.translation)
        tangent_sizes.append(
            0 if problem.is_parameter_block_constant(block)
            else problem.parameter_block_tangent_size(block)
        )
    # TWO_CAMS_FROM_WORLD: one frame constant, one with 5 DOF (fixed baseline length), rest 6.
    assert sorted(tangent_sizes) == [0, 5, 6, 6, 6]
    # Writing the view moves the frame.
    block[4:] += 1.0
    np.testing.assert_allclose(
        reconstruction.frames[frame_id].rig_from_world.translation, block[4:]
    )


def test_position_in_rig_gives_projection_centres():
    reconstruction = _scene(num_cameras_per_rig=2)
    for image_id, image in reconstruction.images.items():
        frame = reconstruction.frames[image.frame_id]
        offset = ceres_blocks.position_in_rig(reconstruction, image_id)
        centre = frame.rig_from_world.inverse() * offset
        np.testing.assert_allclose(centre, image.projection_center(), atol=1e-9)


def test_hybrid_problem_keeps_costs_alive_and_fixes_gnss_drift(core):
    """GNSS priors on the frames pull a shifted block back; costs added through HybridProblem
    survive dropping every other reference (with a temporary `adjuster.problem` they do not)."""
    reconstruction = _scene()
    truth = {
        frame_id: np.array(frame.rig_from_world.inverse().translation)
        for frame_id, frame in reconstruction.frames.items()
    }
    # Gauge free: the GNSS priors alone give the datum (here only the translation matters).
    hybrid = ceres_blocks.HybridProblem(
        _adjuster(reconstruction, pycolmap.BundleAdjustmentGauge.UNSPECIFIED)
    )
    shift = np.array([0.5, -0.3, 0.2])
    for point_id in reconstruction.points3D:
        reconstruction.points3D[point_id].xyz += shift
    for frame_id in reconstruction.frames:
        block = ceres_blocks.frame_pose_block(reconstruction, frame_id)
        rotation = pycolmap.Rotation3d(block[:4])
        block[4:] -= rotation * shift  # centre moves by +shift
        hybrid.add_residual(
            core.ProjectionCenterPriorCost(truth[frame_id], np.full(3, 0.01)), None, [block]
        )
    gc.collect()
    residuals = np.asarray(hybrid.problem.evaluate_residuals())
    gnss = residuals[-3 * len(truth):].reshape(-1, 3)
    np.testing.assert_allclose(gnss, np.tile(shift / 0.01, (len(truth), 1)), atol=1e-6)

    summary = hybrid.solve()
    assert summary.is_solution_usable()
    for frame_id, frame in reconstruction.frames.items():
        centre = frame.rig_from_world.inverse().translation
        assert np.linalg.norm(centre - truth[frame_id]) < 1e-4


def test_add_plane_uses_a_wrapped_sphere_manifold():
    reconstruction = _scene()
    adjuster = _adjuster(reconstruction)
    hybrid = ceres_blocks.HybridProblem(adjuster)
    plane = hybrid.add_plane([0.0, 0.0, 2.0], -4.0)
    np.testing.assert_allclose(plane.normal, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(plane.offset, [-2.0])
    assert hybrid.problem.parameter_block_tangent_size(plane.normal) == 2
    assert hybrid.problem.parameter_block_tangent_size(plane.offset) == 1
    with pytest.raises(ValueError, match="non-zero"):
        hybrid.add_plane([0.0, 0.0, 0.0], 1.0)
    # Destroying COLMAP's problem (which owns manifolds) must not free ours a second time:
    # a double free here aborts the test process.
    del hybrid, adjuster
    gc.collect()


def test_add_residual_rejects_arrays_pyceres_would_copy(core):
    reconstruction = _scene()
    hybrid = ceres_blocks.HybridProblem(_adjuster(reconstruction))
    plane = hybrid.add_plane([0.0, 0.0, 1.0], 0.0)
    with pytest.raises(TypeError, match="float64"):
        hybrid.add_residual(
            core.PointPlaneDistanceCost(0.1),
            None,
            [np.zeros(3, dtype=np.float32), plane.normal, plane.offset],
        )


def test_sensor_from_rig_of_a_non_reference_camera_is_a_block():
    reconstruction = _scene(num_cameras_per_rig=2)
    problem = _adjuster(reconstruction, pycolmap.BundleAdjustmentGauge.UNSPECIFIED).problem
    rig = next(iter(reconstruction.rigs.values()))
    sensors = list(rig.non_ref_sensors)
    assert len(sensors) == 1
    block = ceres_blocks.sensor_from_rig_block(reconstruction, rig.rig_id, sensors[0])
    assert problem.has_parameter_block(block)
    assert problem.parameter_block_tangent_size(block) == 6
    block[4] += 1.0
    np.testing.assert_allclose(rig.sensor_from_rig(sensors[0]).translation[0], block[4])
